"""What every benchmark records beside its figures: the machine, the command, when, and how loaded.

Import it from a bench script as `from bench._common import machine, provenance`; benchmarks run from
the checkout as `python -m bench.NAME`.
"""
from __future__ import annotations

import json
import time
import types
import typing
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

from touchroller_bringup.report import loadavg
from touchroller_bringup.report import machine_description as machine
from touchroller_perception.files import atomic_path, atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"

__all__ = ["RESULTS", "ROOT", "Provenance", "command", "loadavg", "machine", "provenance", "provenance_markdown",
           "results_path", "to_json", "from_json", "load_json", "load_dict", "write_results"]


def subpixel_peak(values: np.ndarray, i: int) -> float:
    """The sub-pixel offset (-0.5..0.5) of a score maximum at index `i` by a parabola through it and its
    neighbours (0 at an edge or where the three do not curve down). The benches' own, so their scores do
    not rest on the mapper's registration code they measure."""
    if 0 < i < len(values) - 1:
        a, b, c = (float(v) for v in values[i - 1:i + 2])
        den = a - 2 * b + c
        if den < 0:
            return float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
    return 0.0


def save_figure(fig: Any, path: Path, **kwargs: Any) -> None:
    """`fig.savefig(path)`, whole or not at all (the format follows the suffix, as savefig's)."""
    with atomic_path(path) as temporary:
        fig.savefig(temporary, format=path.suffix.lstrip(".") or None, **kwargs)


def results_path(name: str, quick: bool, suffix: str = ".md") -> Path:
    """Where a bench writes its figures by default. Quick runs go to `bench/results/quick/` (not
    committed), so a CI-sized check never overwrites the committed full-run figures."""
    return (RESULTS / "quick" if quick else RESULTS) / f"{name}{suffix}"


def command(script: str, quick: bool = False, *extra: str) -> str:
    """The command that reproduces a bench's figures, as a user types it in the checkout."""
    return " ".join([".venv/bin/python", "-m", f"bench.{script}", *(["--quick"] if quick else []), *extra])


@dataclass(frozen=True)
class Provenance:
    """How a bench's figures were obtained: the command that reproduces them, the machine, when, and the
    load average at the start (above the core count, other jobs shared the machine)."""

    command: str
    machine: str
    measured: str
    loadavg: str

    def markdown(self) -> str:
        """Two Markdown lines (hard breaks) for the top of a bench's results and its report section."""
        return (f"Command: `{self.command}`  \n"
                f"Machine: {self.machine}; measured {self.measured}, load average at the start {self.loadavg}.")


def provenance(script: str, quick: bool = False, *extra: str) -> Provenance:
    """Taken when a bench starts, stored in its result and printed by `provenance_markdown`."""
    return Provenance(command(script, quick, *extra), machine(),
                      time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), loadavg())


def provenance_markdown(stamp: Provenance | Mapping[str, Any]) -> str:
    """`Provenance.markdown`; a mapping (a result read back from its JSON file) is read by field name."""
    if not isinstance(stamp, Provenance):
        stamp = Provenance(**{f.name: str(stamp[f.name]) for f in fields(Provenance)})
    return stamp.markdown()


def to_json(result: Any, **kwargs: Any) -> str:
    """A bench result as JSON: dataclasses as objects, numpy scalars and arrays as numbers and lists."""
    return json.dumps(result, default=_plain, **kwargs)


def _plain(value: Any) -> Any:
    if is_dataclass(value) and not isinstance(value, type):
        return asdict(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return float(value)   # anything else number-like; a TypeError names what cannot be written


def from_json(kind: Any, data: Any) -> Any:
    """`data` (parsed JSON, as `to_json` wrote it) rebuilt as `kind`: a dataclass (fields by their type hints,
    nested), tuple[X, ...], tuple[X, Y], list[X], dict[str, X], X | None, numpy arrays, numbers and strings.
    Every bench's `load` is this on its result type, so the report can render any section from its recording."""
    if data is None or kind is Any:
        return data
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in args if a is not type(None)]
        for option in options:
            try:
                return from_json(option, data)
            except (TypeError, ValueError, KeyError):
                continue
        raise TypeError(f"{data!r} fits none of {kind}")
    if is_dataclass(kind) and isinstance(kind, type):
        if not isinstance(data, Mapping):
            raise TypeError(f"{kind.__name__} from {type(data).__name__}")
        hints = typing.get_type_hints(kind)
        return kind(**{f.name: from_json(hints[f.name], data[f.name]) for f in fields(kind) if f.init
                       and f.name in data})
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(from_json(args[0], v) for v in data)
        return tuple(from_json(a, v) for a, v in zip(args, data, strict=True)) if args else tuple(data)
    if origin is list:
        return [from_json(args[0], v) for v in data] if args else list(data)
    if origin in (dict, Mapping) or kind is dict:
        value_kind = args[1] if args else Any
        return {k: from_json(value_kind, v) for k, v in data.items()}
    if kind is np.ndarray:
        return np.asarray(data)
    if kind is float:
        return float(data)
    if kind is int and not isinstance(data, int):
        raise TypeError(f"int from {data!r}")
    if kind in (int, str, bool) and not isinstance(data, kind):
        raise TypeError(f"{kind.__name__} from {data!r}")
    if kind is Path:
        return Path(data)
    return data


def load_json(kind: Any, path: Path) -> Any:
    """A result a bench wrote with `to_json`, read back as `kind` (see `from_json`)."""
    return from_json(kind, json.loads(Path(path).read_text(encoding="utf-8")))


def load_dict(path: Path) -> dict[str, Any]:
    """A result a bench wrote as a plain JSON object, for the report to render without running it again
    (the `load` of the benches whose results are string-keyed tables)."""
    result: dict[str, Any] = load_json(dict, path)
    return result


def write_results(out: Path, title: str, result: Any, to_markdown: Any, figures: Any = None) -> None:
    """A bench's recorded run: `out` (Markdown under `# title`), the JSON beside it that the report
    renders from, then the bench's figures into the same folder; each file whole or not at all."""
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, f"# {title}\n\n" + to_markdown(result))
    atomic_write_text(out.with_suffix(".json"), to_json(result, indent=1))
    for figure in (figures(result, out.parent) if figures is not None else []):
        print(f"wrote {figure}")
