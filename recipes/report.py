"""The results pages from the files under results/: ``python recipes/report.py``.

    python recipes/report.py                  # every block of every page (docs/results/*.md, README.md's
                                              # headline) and their figures
    python recipes/report.py --block table2   # one block, in each page that holds it
    python recipes/report.py --check          # exit 1 when a page's block differs from what results/ gives
    python recipes/report.py --results results/my_sweep --out /tmp/table1.md   # Table 1 of a sweep of one's own

The pages and their blocks are data (``recipes/reporting/pages.yaml``), the paper's figures too
(``recipes/reporting/paper.yaml``); ``torchrl_silp.recipes.reporting`` renders them.
"""

from __future__ import annotations

import sys

from torchrl_silp.recipes.reporting.pages import main

if __name__ == "__main__":
    try:
        main()
    except FileNotFoundError as exc:
        sys.exit(f"report.py: {exc}")
