"""Recording size and `touchroller map` speed: raw recordings against the compressed ones `touchroller record`
and `touchroller scan --record` write (PNG CompressedImage on image_raw/compressed, zstd MCAP chunks but
for those of PNG frames).

Two sources film a 3-pass raster with /tf and /tf_static: the simulator (`bench.world_map.make_bag`, as
`touchroller scan --record` holds it) and the second raster generator (`bench.raster_generator`, which
imports nothing of the simulator: its own surface, shading and noise). Each raw recording is rewritten
every way (`touchroller_bringup.bag_compression.compress_recording`); for each: bytes per frame, per square
metre mapped (the map's mapped cells from `touchroller map`), the time to compress a frame, and
`touchroller map` as a whole command (a new process, best of the repeats), whose map must be identical to
the raw recording's (lossless).

    .venv/bin/python -m bench.recording_size [--quick]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from bench._common import ROOT, Provenance, provenance, provenance_markdown, results_path, to_json
from touchroller_perception.files import atomic_write_text

FULL = {"length": 0.08, "repeats": 2}
QUICK = {"length": 0.025, "repeats": 1}
#: (name, storage, PNG images, zstd chunks)
VARIANTS = (("sqlite3 raw", "sqlite3", False, False), ("MCAP raw", "mcap", False, False),
            ("MCAP zstd chunks", "mcap", False, True), ("sqlite3 PNG", "sqlite3", True, False),
            ("MCAP PNG + zstd chunks", "mcap", True, True))
DEFAULT = "sqlite3 PNG"   # what `touchroller record` / `scan --record` write with the default storage


@dataclass(frozen=True)
class Variant:
    name: str
    storage: str
    png: bool
    zstd: bool
    bytes: int
    frames: int
    write_s: float            # rewriting the raw recording this way (0 for the source itself)
    map_s: float              # `touchroller map` as a new process, best of the repeats
    same_map: bool            # map.png identical to the raw recording's

    @property
    def bytes_per_frame(self) -> float:
        return self.bytes / max(self.frames, 1)

    @property
    def map_fps(self) -> float:
        return self.frames / self.map_s if self.map_s > 0 else float("nan")


@dataclass(frozen=True)
class Source:
    name: str
    mapped_m2: float          # the map's mapped cells x resolution^2
    variants: list[Variant]

    def variant(self, name: str) -> Variant:
        return next(v for v in self.variants if v.name == name)

    def per_m2(self, v: Variant) -> float:
        return v.bytes / self.mapped_m2 if self.mapped_m2 > 0 else float("nan")


@dataclass(frozen=True)
class RecordingResult:
    provenance: Provenance
    quick: bool
    length: float
    repeats: int
    sources: list[Source]


def _bag_bytes(bag: Path) -> int:
    return sum(p.stat().st_size for p in bag.rglob("*") if p.is_file())


def _timed(argv: list[str], env: dict[str, str]) -> float:
    start = time.perf_counter()
    subprocess.run(argv, check=True, capture_output=True, cwd=ROOT, env=env)
    return time.perf_counter() - start


def _mapped_m2(map_png: Path) -> float:
    import yaml

    image = cv2.imread(str(map_png), cv2.IMREAD_UNCHANGED)
    resolution = float(yaml.safe_load(map_png.with_suffix(".yaml").read_text())["resolution"])
    alpha = image[..., -1] if image.ndim == 3 else np.full(image.shape, 255, np.uint8)
    return float(np.count_nonzero(alpha)) * resolution ** 2


def measure(name: str, raw: Path, tmp: Path, repeats: int) -> Source:
    from touchroller_bringup.bag_compression import compress_recording
    from touchroller_bringup.bags import read_images

    frames = sum(1 for _ in read_images(raw))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPYCACHEPREFIX"] = str(tmp / "pycache")
    bags: list[tuple[tuple[str, str, bool, bool], Path, float]] = []
    for variant in VARIANTS:
        label, storage, png, zstd = variant
        if (storage, png, zstd) == ("sqlite3", False, False):
            bags.append((variant, raw, 0.0))
            continue
        target = tmp / f"{name}_{label.replace(' ', '_').replace('+', '')}"
        start = time.perf_counter()
        compress_recording(raw, target, storage=storage, png=png, zstd=zstd)
        bags.append((variant, target, time.perf_counter() - start))
    command = [sys.executable, "-m", "touchroller_bringup.cli", "map"]
    if repeats > 1:   # the bytecode cache, once (a quick run's single timing is not judged)
        _timed([*command, str(raw), "--out", str(tmp / "warm.png")], env)
    times: dict[Path, float] = {bag: float("inf") for _, bag, _ in bags}
    for k in range(repeats):   # interleaved: a loaded machine slows every variant alike
        for _, bag, _ in bags:
            times[bag] = min(times[bag], _timed([*command, str(bag), "--out", str(tmp / f"m{k}_{bag.name}.png")],
                                                env))
    reference = cv2.imread(str(tmp / f"m0_{raw.name}.png"), cv2.IMREAD_UNCHANGED)
    variants = []
    for (label, storage, png, zstd), bag, write_s in bags:
        mapped = cv2.imread(str(tmp / f"m0_{bag.name}.png"), cv2.IMREAD_UNCHANGED)
        same = mapped is not None and mapped.shape == reference.shape and bool(np.array_equal(mapped, reference))
        variants.append(Variant(label, storage, png, zstd, _bag_bytes(bag), frames, write_s, times[bag], same))
    return Source(name, _mapped_m2(tmp / f"m0_{raw.name}.png"), variants)


def run(quick: bool = False) -> RecordingResult:
    from bench.raster_generator import RasterSpec, generate
    from bench.world_map import make_bag

    size = QUICK if quick else FULL
    stamp = provenance("recording_size", quick)
    tmp = Path(tempfile.mkdtemp(prefix="recording_size_"))
    try:
        make_bag(tmp / "sim", size["length"])
        generate(RasterSpec(corner=(0.42, -0.07), length=size["length"], width=0.14, passes=3), tmp / "second")
        sources = [measure("simulator", tmp / "sim", tmp, size["repeats"]),
                   measure("second generator", tmp / "second" / "bag", tmp, size["repeats"])]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return RecordingResult(stamp, quick, size["length"], size["repeats"], sources)


def goals(r: RecordingResult) -> list[tuple[str, str, bool | None]]:
    """(goal, figure, met) rows for the report."""
    rows: list[tuple[str, str, bool | None]] = []
    for source in r.sources:
        raw, packed = source.variant("sqlite3 raw"), source.variant(DEFAULT)
        rows.append((f"Recordings lossless and smaller than raw ({source.name}): `touchroller record`'s default",
                     f"{packed.bytes_per_frame / 1e3:.0f} kB per frame against {raw.bytes_per_frame / 1e3:.0f} kB "
                     f"({packed.bytes / raw.bytes:.2f}x), {source.per_m2(packed) / 1e9:.1f} GB per m^2 mapped; "
                     f"same map: {'yes' if all(v.same_map for v in source.variants) else 'NO'}",
                     all(v.same_map for v in source.variants) and packed.bytes < raw.bytes))
    return rows


def to_markdown(r: RecordingResult) -> str:
    lines = [provenance_markdown(r.provenance), "",
             f"A 3-pass raster, {r.length * 100:.0f} cm along, 14 cm across, with /tf and /tf_static; `touchroller "
             f"map` as a new process, best of {r.repeats}. Bytes per m^2 are of the area the map covers.", ""]
    for source in r.sources:
        raw = source.variant("sqlite3 raw")
        lines += [f"### {source.name} ({raw.frames} frames, {source.mapped_m2 * 1e4:.0f} cm^2 mapped)", "",
                  "| recording | kB per frame | x raw | GB per m^2 | writing ms per frame | `touchroller map` "
                  "frames/s | same map |",
                  "|---|---|---|---|---|---|---|"]
        for v in source.variants:
            lines.append(f"| {v.name}{' (default)' if v.name == DEFAULT else ''} | {v.bytes_per_frame / 1e3:.1f} | "
                         f"{v.bytes / raw.bytes:.2f} | {source.per_m2(v) / 1e9:.1f} | "
                         f"{v.write_s / max(v.frames, 1) * 1e3:.1f} | {v.map_fps:.0f} | "
                         f"{'yes' if v.same_map else 'NO'} |")
        lines.append("")
    lines += ["Writing is the rewrite of the raw recording (reading it, PNG Huffman-coded at zlib level 1, zstd "
              "level 1 chunks), on one core; the recorder does the same on its writer thread. `touchroller "
              "map` reads raw sqlite3 recordings by rows (only the band's); MCAP and PNG recordings are read and "
              "decoded whole.",
              "", "### Goals", ""]
    lines += [f"- {goal}: {figure} ({'met' if met else 'NOT met' if met is False else 'no verdict'})"
              for goal, figure, met in goals(r)]
    return "\n".join(lines) + "\n"


def load(path: Path) -> RecordingResult:
    """A result written by this bench (its JSON), to render again."""
    data = json.loads(Path(path).read_text(encoding="utf-8"))
    sources = [Source(s["name"], s["mapped_m2"], [Variant(**v) for v in s["variants"]]) for s in data["sources"]]
    return RecordingResult(Provenance(**data["provenance"]), data["quick"], data["length"], data["repeats"], sources)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"a {QUICK['length'] * 100:.0f} cm raster, one run")
    parser.add_argument("--out", type=Path, help="results file, + .json beside it (default: "
                        "bench/results/recording_size.md, quick/ with --quick)")
    args = parser.parse_args(argv)
    result = run(args.quick)
    text = "# Recording size and `touchroller map` speed: raw against compressed\n\n" + to_markdown(result)
    out = args.out or results_path("recording_size", args.quick)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out.with_suffix(".json"), to_json(result, indent=1))
    atomic_write_text(out, text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
