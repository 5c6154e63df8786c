"""Print the table of decision numbers (configs/default.yaml's status, lifecycle and estimator keys, with
unit and how each was chosen, and the count) that README.md shows; ``--check`` compares it with the README.

Usage: .venv/bin/python scripts/decision_numbers.py [--check README.md]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app import decision_numbers  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", metavar="README", help="exit 1 unless this file holds the table as printed")
    a = ap.parse_args()
    table = decision_numbers.markdown_table()
    if a.check:
        if table not in Path(a.check).read_text():
            print(f"{a.check} does not hold the current table of decision numbers: paste this output there", file=sys.stderr)
            print(table)
            return 1
        return 0
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
