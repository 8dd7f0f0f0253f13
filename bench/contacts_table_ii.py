"""The paper's Table II (contact localisation error) reproduced in simulation, with its error budget.

Runs `bench.table_ii.table_ii` (simulator scene contact_localisation when
installed; its `our_calibration` condition calibrates on simulated calibration images per seed and
locates the taps with the camera found) and `explain_paper_table`, and writes
bench/results/contacts_table_ii.md (+ .json)
(`python -m bench.contacts_table_ii [--quick]`; the report generator calls `run` and `to_markdown`).
Not a timing benchmark: the figures are errors in mm and do not depend on the machine.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from bench._common import command, load_dict, results_path, save_figure, write_results
from bench.table_ii import (
    explain_markdown,
    explain_paper_table,
    table_ii,
    table_ii_markdown,
)
from touchroller_driver.sim import SimulatedSensor, load_scene


def run(quick: bool = False) -> dict[str, Any]:
    result = table_ii(quick=quick)
    camera = load_scene("contact_localisation").camera
    return {"table_ii": result, "paper_fit": explain_paper_table(camera), "quick": quick}


def to_markdown(result: dict[str, Any]) -> str:
    text = table_ii_markdown(result["table_ii"], command("contacts_table_ii", result["quick"]))
    text = text.split("\n", 2)[2] if text.startswith("# ") else text     # the caller gives the title
    return text + "\n" + explain_markdown(result["paper_fit"])


def figures(result: dict[str, Any], out_dir: Path) -> list[Path]:
    """Per-cell error beside the paper's (log scale), and one simulated tap with the two detectors' centres."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = result["table_ii"]["rows"]
    names = [n for n in ("exact", "paper_detector", "error_sources", "our_calibration") if n in rows[0]]
    labels = [f"{r['alpha']}\n{r['fraction']:g}L" for r in rows]
    x = np.arange(len(rows))
    width = 0.8 / (len(names) + 1)
    fig, ax = plt.subplots(figsize=(11, 4.8))
    ax.bar(x - 0.4 + width / 2, [r["paper_mean_mm"] for r in rows], width, label="paper (hardware)", color="0.6")
    legend = {"error_sources": "error_sources (the paper's calibration error)",
              "our_calibration": "our_calibration (recalibrated per seed)"}
    for k, name in enumerate(names, start=1):
        ax.bar(x - 0.4 + width / 2 + k * width, [max(r[name]["mean_mm"], 1e-4) for r in rows], width,
               label=legend.get(name, name))
    ax.set_yscale("log")
    ax.set_ylabel("Euclidean error, mm")
    ax.set_xticks(x, labels, fontsize=7)
    ax.axhline(0.25, color="k", lw=0.8, ls="--", label="goal 0.25 mm")
    ax.axhline(1.0, color="tab:red", lw=0.8, ls=":", label="aim: sub-millimetre")
    ax.legend(fontsize=7, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.16))
    ax.set_title("Table II cells: central angle x axial position")
    fig.tight_layout()
    paths = [out_dir / "contacts_table_ii_cells.png"]
    save_figure(fig, paths[0], dpi=110)
    plt.close(fig)
    example = _detection_example()
    if example is not None:
        crop, marks = example
        fig, ax = plt.subplots(figsize=(4.2, 4.2))
        ax.imshow(crop[..., ::-1], interpolation="nearest")
        for (u, v), style, label in marks:
            ax.plot(u, v, style, ms=10, mew=2, label=label)
        ax.legend(fontsize=7, loc="lower left")
        ax.set_title("one simulated tap (crop, 1 px = 1 px)", fontsize=9)
        ax.axis("off")
        fig.tight_layout()
        paths.append(out_dir / "contacts_detection_example.png")
        save_figure(fig, paths[1], dpi=110)
        plt.close(fig)
    return paths


def _detection_example():
    from touchroller_perception.contacts import ContactDetector, DetectorConfig

    frames = list(SimulatedSensor(load_scene("contact_localisation", **{"motion.repeats": 1}), seed=0).frames())
    references = [f.image for f in frames if f.truth.get("phase") == "reference"]
    tap = next(f for f in frames if f.truth.get("phase") == "tap")
    u, v = tap.truth["contacts"][0]["pixel"]
    marks = [((u, v), "w+", "truth")]
    for method, style in (("colour", "cx"), ("paper", "m1")):
        detector = ContactDetector(DetectorConfig(method=method))
        detector.set_reference(references)
        found = detector.detect(tap.image)
        if found:
            best = min(found, key=lambda c: (c.u - u) ** 2 + (c.v - v) ** 2)
            marks.append(((best.u, best.v), style, f"{method} detector"))
    half = 24
    u0, v0 = int(round(u)) - half, int(round(v)) - half
    crop = tap.image[max(v0, 0):v0 + 2 * half, max(u0, 0):u0 + 2 * half]
    return crop, [((mu - max(u0, 0), mv - max(v0, 0)), style, label) for (mu, mv), style, label in marks]

load = load_dict   # the report reads the recorded JSON back through the bench's `load`



def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 taps per cell, main conditions only")
    parser.add_argument("--out", help="results file (default: bench/results/contacts_table_ii.md, quick/ with --quick)")
    args = parser.parse_args(argv)
    result = run(quick=args.quick)
    out = Path(args.out) if args.out else results_path("contacts_table_ii", args.quick)
    write_results(out, "Contact localisation: the paper's Table II in simulation", result, to_markdown, figures)
    summary = result["table_ii"]["summary"]
    print(f"exact calibration: mean {summary['exact']['mean_mm']:.4f} mm, worst cell "
          f"{summary['exact']['max_cell_mean_mm']:.4f} mm (goal <= 0.25 mm); wrote {out}")
    for name in ("error_sources", "our_calibration"):
        if name in summary:
            print(f"{name}: mean {summary[name]['mean_mm']:.3f} mm, "
                  f"worst cell {summary[name]['max_cell_mean_mm']:.3f} mm"
                  + (f" (worst cell of a single seed {summary[name]['worst_seed_max_cell_mean_mm']:.3f} mm)"
                     if "worst_seed_max_cell_mean_mm" in summary[name] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
