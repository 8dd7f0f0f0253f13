"""The paper's Table II (contact localisation error) reproduced in simulation, with its error budget.

Runs `touchroller_perception.localisation.table_ii` (simulator scene contact_localisation when
installed) and `explain_paper_table`, and writes bench/results/contacts_table_ii.md (+ .json).
Not a timing benchmark: the figures are errors in mm and do not depend on the machine.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 taps per cell, main conditions only")
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args(argv)
    result = table_ii(quick=args.quick)
    try:
        from touchroller_driver.sim import load_scene

        camera = load_scene("contact_localisation").camera
    except ImportError:
        camera = TABLE_II_CAMERA
    fit = explain_paper_table(camera)
    command = "python bench/contacts_table_ii.py" + (" --quick" if args.quick else "")
    text = table_ii_markdown(result, command) + "\n" + explain_markdown(fit)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    out.with_suffix(".json").write_text(json.dumps({"table_ii": result, "paper_fit": fit}, indent=1,
                                                   default=float), encoding="utf-8")
    summary = result["summary"]
    print(f"exact calibration: mean {summary['exact']['mean_mm']:.4f} mm, worst cell "
          f"{summary['exact']['max_cell_mean_mm']:.4f} mm (goal <= 0.25 mm); wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
