"""Contacts on real GelSight presses: found, centre error, false contacts and time per frame, ours vs the paper's.

Data: the `taxim` wheel's labelled presses (bench/real_presses.py): the GelSight Mini (24 presses;
knobs tuned on the even ones, the odd ones held out) and an older GelSight (48 presses, never tuned
on). Each sensor's one no-contact frame is the whole reference. Per press: the contact whose centre
lies inside the labelled disc (nearest to the label) is the match, every other contact a false one.
Time: `ContactDetector.detect` per 640x480 frame, best of several runs per frame, median over the
frames, OpenCV on one thread. Goals (issue 13): all presses found, median centre error <= 5 px, no
false contact, <= 1 ms per frame.

Results: bench/results/contacts_real.md (`python -m bench.contacts_real [--quick]`; the report
generator calls `run`, `to_markdown` and `figures`).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench._common import provenance, provenance_markdown, results_path, save_figure
from bench.real_presses import SENSORS, Scorecard, available, load_presses, score
from touchroller_perception.contacts import DetectorConfig
from touchroller_perception.files import atomic_write_text

METHODS = {"ours (colour)": DetectorConfig(), "paper's pipeline": DetectorConfig(method="paper")}
#: the Mini's presses come in two runs at two indenter positions along u (see `label_scatter`)
MINI_RUNS = (range(0, 13), range(13, 24))


def _summary(card: Scorecard) -> dict[str, Any]:
    mm = card.mm_per_pixel
    return {"presses": card.presses, "found": card.found, "median_px": card.median_px, "p90_px": card.p90_px,
            "median_mm": card.median_px * mm, "p90_mm": card.p90_px * mm, "false_contacts": card.false_contacts,
            "false_per_frame": card.false_per_frame, "median_ms": card.median_ms}


def _per_press(card: Scorecard, presses) -> list[dict[str, Any]]:
    rows = []
    for r in card.results:
        c = r.contact
        rows.append({"index": r.index, "label_u": float(presses.centres[r.index][0]),
                     "label_v": float(presses.centres[r.index][1]), "radius": float(presses.radii[r.index]),
                     "u": c.u if c else float("nan"), "v": c.v if c else float("nan"), "error_px": r.error_px,
                     "false": r.false_contacts, "ms": 1e3 * r.seconds,
                     "area": c.area if c else float("nan"), "score": c.score if c else float("nan")})
    return rows


def label_scatter(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per run of Mini presses at one indenter position: the spread of u of our centres and of the labels."""
    out = []
    for run in MINI_RUNS:
        ours = np.array([rows[i]["u"] for i in run])
        labels = np.array([rows[i]["label_u"] for i in run])
        out.append({"presses": f"{run.start}-{run.stop - 1}", "ours_u_std": float(np.nanstd(ours)),
                    "labels_u_std": float(np.std(labels)), "ours_u_mean": float(np.nanmean(ours)),
                    "labels_u_mean": float(np.mean(labels))})
    return out


def run(quick: bool = False) -> dict[str, Any]:
    stamp = provenance("contacts_real", quick)
    if not available():
        raise RuntimeError("the taxim wheel (real GelSight presses) is not installed: pip install -r requirements.txt")
    cv2.setNumThreads(1)
    repeats = 3 if quick else 10
    sensors = []
    for sensor in SENSORS:
        presses = load_presses(sensor)
        methods = []
        for name, config in METHODS.items():
            card = score(presses, config, repeats=repeats)
            entry: dict[str, Any] = {"method": name, "all": _summary(card), "per_press": _per_press(card, presses)}
            if sensor == "gelsight_mini":
                entry["tuning"] = _summary(card.subset(presses.tuning))
                entry["held_out"] = _summary(card.subset(presses.held_out))
            methods.append(entry)
            print(f"{sensor:14s} {name:18s} found {card.found}/{card.presses}  median {card.median_px:.2f} px  "
                  f"p90 {card.p90_px:.2f} px  false {card.false_contacts}  {card.median_ms:.3f} ms", flush=True)
        sensors.append({"sensor": sensor, "mm_per_pixel": presses.mm_per_pixel, "presses": len(presses),
                        "methods": methods})
    mini = next(s for s in sensors if s["sensor"] == "gelsight_mini")
    return {"sensors": sensors, "label_scatter": label_scatter(mini["methods"][0]["per_press"]),
            "repeats": repeats, "quick": quick, "provenance": stamp}


def ours(result: dict[str, Any], sensor: str = "gelsight_mini", part: str = "all") -> dict[str, Any]:
    """Our detector's summary on `sensor` ("all", or for the Mini "tuning" / "held_out")."""
    entry = next(s for s in result["sensors"] if s["sensor"] == sensor)
    return entry["methods"][0][part]


def _row(label: str, s: dict[str, Any]) -> str:
    return (f"| {label} | {s['found']}/{s['presses']} | {s['median_px']:.2f} ({s['median_mm']:.3f}) | "
            f"{s['p90_px']:.2f} ({s['p90_mm']:.3f}) | {s['false_contacts']} ({s['false_per_frame']:.2f}) | "
            f"{s['median_ms']:.3f} |")


def to_markdown(result: dict[str, Any]) -> str:
    lines = [provenance_markdown(result["provenance"]), "",
             f"Reference: each sensor's one no-contact frame. Time: best of {result['repeats']} runs per 640x480 "
             "frame, median over the presses, OpenCV on one thread.", "",
             "| sensor, presses | method | found | centre error median, px (mm) | p90, px (mm) | "
             "false contacts (per frame) | ms per frame |", "|---|---|---|---|---|---|---|"]
    for s in result["sensors"]:
        for m in s["methods"]:
            parts = [("all", f"{s['sensor']}, all {s['presses']}")]
            if "tuning" in m:
                parts += [("tuning", f"{s['sensor']}, tuning (even)"), ("held_out", f"{s['sensor']}, held out (odd)")]
            for key, label in parts:
                lines.append(_row(f"{label} | {m['method']}", m[key]))
    mini = ours(result)
    lines += ["", "Goals on the GelSight Mini (all 24 presses, our detector):",
              f"- all presses found: **{'met' if mini['found'] == mini['presses'] else 'NOT met'}** "
              f"({mini['found']}/{mini['presses']})",
              f"- median centre error <= 5 px: **{'met' if mini['median_px'] <= 5 else 'NOT met'}** "
              f"({mini['median_px']:.2f} px against the hand labels; see the label scatter below)",
              f"- no false contact: **{'met' if mini['false_contacts'] == 0 else 'NOT met'}** "
              f"({mini['false_contacts']})",
              f"- <= 1 ms per frame: **{'met' if mini['median_ms'] <= 1.0 else 'NOT met'}** "
              f"({mini['median_ms']:.3f} ms)",
              "", "### How precise are the labels?", "",
              "The Mini's presses were made in two runs, each at one indenter position along u. Within a run our "
              "centres keep u to a fraction of a pixel; the hand-placed labels of the same presses scatter by "
              "several pixels, which puts a floor under any detector's error against them:", "",
              "| presses | std of our u, px | std of the labels' u, px | mean u ours / labels, px |",
              "|---|---|---|---|"]
    for r in result["label_scatter"]:
        lines.append(f"| {r['presses']} | {r['ours_u_std']:.2f} | {r['labels_u_std']:.2f} | "
                     f"{r['ours_u_mean']:.1f} / {r['labels_u_mean']:.1f} |")
    lines += ["", "The older GelSight's labels follow the image more closely: there the same detector's median "
              "error is a few pixels.", "", "### Per press (our detector)", "",
              "| sensor | press | label (u, v), radius px | ours (u, v) | error px | false | score | area px² |",
              "|---|---|---|---|---|---|---|---|"]
    for s in result["sensors"]:
        for p in s["methods"][0]["per_press"]:
            lines.append(f"| {s['sensor']} | {p['index']} | "
                         f"({p['label_u']:.0f}, {p['label_v']:.0f}), {p['radius']:.0f} "
                         f"| ({p['u']:.1f}, {p['v']:.1f}) | {p['error_px']:.2f} | {p['false']} | {p['score']:.0f} "
                         f"| {p['area']:.0f} |")
    return "\n".join(lines) + "\n"


def figures(result: dict[str, Any], out_dir: Path) -> list[Path]:
    """Centre error per press, ours and the paper's, for both sensors."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, len(result["sensors"]), figsize=(12, 3.8))
    for ax, s in zip(np.atleast_1d(axes), result["sensors"], strict=True):
        for m, colour in zip(s["methods"], ("tab:blue", "tab:red"), strict=True):
            rows = m["per_press"]
            ax.plot([p["index"] for p in rows], [p["error_px"] for p in rows], "o", ms=4, color=colour,
                    label=f"{m['method']}: median {m['all']['median_px']:.1f} px, "
                          f"{m['all']['found']}/{m['all']['presses']}"
                          f" found, {m['all']['false_contacts']} false")
        ax.axhline(5.0, color="k", lw=0.8, ls="--", label="goal: median 5 px")
        ax.set_yscale("log")
        ax.set_xlabel("press")
        ax.set_ylabel("centre error against the label, px")
        ax.set_title(f"{s['sensor']} ({s['presses']} presses, one reference frame)", fontsize=10)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    path = out_dir / "contacts_real.png"
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return [path]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer timing repeats")
    parser.add_argument("--out", help="results file (default: bench/results/contacts_real.md, quick/ with --quick)")
    args = parser.parse_args(argv)
    result = run(quick=args.quick)
    out = Path(args.out) if args.out else results_path("contacts_real", args.quick)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, "# Contacts on real GelSight presses\n\n" + to_markdown(result))
    for figure in figures(result, out.parent):
        print(f"wrote {figure}")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
