"""Imprint centres under light from one side: how far each centre estimator moves with the light.

The hemisphere presses of `bench.calib_lighting` (the simulator's sphere-cap imprints under one white
LED at 25 deg, the second renderer's Hertzian imprints under its LED at 35 deg, and the second
renderer's centred frame under an LED at 15 deg), lit from each of 4 azimuths, and each imprint's
centre found by each estimator of `ImprintDetectorConfig.centre` against the true imprint centre:
the mean error along the direction to the light (+: pulled towards it) and across it, over every
imprint of every seed. A centre that does not move with the light's direction stays near 0 on every
side; one that does moves the same way for each azimuth, which is the error every press shares and
the pose solve turns into theta (along v) or a shift (along u).

`python -m bench.calib_centres [--quick]` writes bench/results/calib_centres.{md,json}.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from bench import calib_lighting as lighting
from bench._common import Provenance, provenance, provenance_markdown, results_path, write_results
from bench.calib_crosscheck import centre_errors

TITLE = "Imprint centres under light from one side"
ESTIMATORS = ("centroid", "symmetric", "shading")
#: the centre's mean pull (px), any direction, on every renderer and light side
GOAL_PX = 0.1


@dataclasses.dataclass(frozen=True)
class Cell:
    renderer: str
    azimuth_deg: float
    centre: str
    imprints: int
    towards_px: float     # mean error along the direction to the light (+: towards it)
    across_px: float      # mean error across it (+: 90 deg counter-clockwise from it in the image)
    spread_px: float      # RMS over imprints of the error less its mean (both axes)

    @property
    def pull_px(self) -> float:
        return math.hypot(self.towards_px, self.across_px)


@dataclasses.dataclass(frozen=True)
class CentresResult:
    provenance: Provenance
    quick: bool
    seeds: int
    presses: int
    cells: tuple[Cell, ...]

    def renderers(self) -> list[str]:
        return [r for r in lighting.RENDERERS if any(c.renderer == r for c in self.cells)]

    def worst(self, renderer: str, centre: str = "shading") -> float:
        """The largest mean pull (px) over the light's azimuths."""
        return max((c.pull_px for c in self.cells if c.renderer == renderer and c.centre == centre),
                   default=math.inf)

    def met(self) -> bool:
        return all(self.worst(r) <= GOAL_PX for r in self.renderers())


def cell(renderer: str, azimuth: float, centre: str, errors: np.ndarray) -> Cell:
    """`errors`: (n, 2) found - true centres (px) of every imprint lit from `azimuth`."""
    towards = np.array([math.cos(math.radians(azimuth)), math.sin(math.radians(azimuth))])
    across = np.array([-towards[1], towards[0]])
    mean = errors.mean(axis=0)
    spread = float(np.sqrt(((errors - mean) ** 2).sum(axis=1).mean()))
    return Cell(renderer, azimuth, centre, len(errors), float(mean @ towards), float(mean @ across), spread)


def run(quick: bool = False, progress: Callable[[str], None] = lambda _: None) -> CentresResult:
    """Quick: 1 seed of 3 presses; full: 3 seeds of 10 presses per renderer and azimuth."""
    stamp = provenance("calib_centres", quick)
    seeds, count = (1, 3) if quick else (3, 10)
    cells = []
    for renderer in lighting.RENDERERS:
        for azimuth in lighting.AZIMUTHS:
            sets = [lighting.PRESSES[renderer](seed, azimuth) for seed in range(seeds)]
            sets = [dataclasses.replace(s, images=s.images[:count], centres_px=s.centres_px[:count]) for s in sets]
            for centre in ESTIMATORS:
                found = cell(renderer, azimuth, centre, np.concatenate([centre_errors(s, centre) for s in sets]))
                cells.append(found)
                progress(f"{renderer} {azimuth:.0f}° {centre}: towards the light {found.towards_px:+.3f} px, "
                         f"across {found.across_px:+.3f} px")
    return CentresResult(stamp, quick, seeds, count, tuple(cells))


def markdown(result: CentresResult) -> list[str]:
    lines = [f"Imprint centres against the truth, {result.seeds} seed(s) x {result.presses} presses of the 2x5 frame "
             "per renderer and light azimuth (0°: light from +u, 90°: from +v). Mean error towards the light "
             "(+: pulled towards it) and across it, px; spread: RMS of each imprint's error about that mean.", "",
             "| renderer | light from | centre | imprints | towards the light (px) | across (px) | spread (px) |",
             "|---|---|---|---|---|---|---|"]
    for c in result.cells:
        lines.append(f"| {c.renderer} | {c.azimuth_deg:.0f}° | {c.centre} | {c.imprints} | {c.towards_px:+.3f} | "
                     f"{c.across_px:+.3f} | {c.spread_px:.3f} |")
    lines += ["", f"| renderer | worst mean pull, shading (goal {GOAL_PX} px) | symmetric | centroid | met |",
              "|---|---|---|---|---|"]
    for r in result.renderers():
        lines.append(f"| {r} | {result.worst(r):.3f} px | {result.worst(r, 'symmetric'):.3f} px | "
                     f"{result.worst(r, 'centroid'):.3f} px | {'yes' if result.worst(r) <= GOAL_PX else 'no'} |")
    return lines


def to_markdown(result: CentresResult) -> str:
    return "\n".join([provenance_markdown(result.provenance), "", *markdown(result)])


def load(path: Path) -> CentresResult:
    """A result written by `main` (its JSON), e.g. for the report."""
    data = json.loads(Path(path).read_text())
    return CentresResult(Provenance(**data["provenance"]), bool(data["quick"]), int(data["seeds"]),
                         int(data["presses"]), tuple(Cell(**c) for c in data["cells"]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 seed of 3 presses (indicative only)")
    args = parser.parse_args()
    result = run(quick=args.quick, progress=lambda line: print(line, file=sys.stderr, flush=True))
    write_results(results_path("calib_centres", args.quick), TITLE, result, to_markdown)
    print(to_markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
