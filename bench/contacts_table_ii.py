"""The paper's Table II (contact localisation error) reproduced in simulation, with its error budget.

Runs `touchroller_perception.localisation.table_ii` (simulator scene contact_localisation when
installed) and `explain_paper_table`, and writes bench/results/contacts_table_ii.md (+ .json)
(`python bench/contacts_table_ii.py [--quick]`; the report generator calls `run` and `to_markdown`).
Not a timing benchmark: the figures are errors in mm and do not depend on the machine.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from touchroller_perception.localisation import (  # noqa: E402
    TABLE_II_CAMERA,
    explain_markdown,
    explain_paper_table,
    table_ii,
    table_ii_markdown,
)

RESULTS = ROOT / "bench" / "results" / "contacts_table_ii.md"


def run(quick: bool = False) -> dict[str, Any]:
    result = table_ii(quick=quick)
    try:
        from touchroller_driver.sim import load_scene

        camera = load_scene("contact_localisation").camera
    except ImportError:
        camera = TABLE_II_CAMERA
    return {"table_ii": result, "paper_fit": explain_paper_table(camera), "quick": quick}


def to_markdown(result: dict[str, Any]) -> str:
    command = "python bench/contacts_table_ii.py" + (" --quick" if result["quick"] else "")
    text = table_ii_markdown(result["table_ii"], command)
    text = text.split("\n", 2)[2] if text.startswith("# ") else text     # the caller gives the title
    return text + "\n" + explain_markdown(result["paper_fit"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 taps per cell, main conditions only")
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args(argv)
    result = run(quick=args.quick)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("# Contact localisation: the paper's Table II in simulation\n\n" + to_markdown(result),
                   encoding="utf-8")
    out.with_suffix(".json").write_text(json.dumps(result, indent=1, default=float), encoding="utf-8")
    summary = result["table_ii"]["summary"]
    print(f"exact calibration: mean {summary['exact']['mean_mm']:.4f} mm, worst cell "
          f"{summary['exact']['max_cell_mean_mm']:.4f} mm (goal <= 0.25 mm); wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
