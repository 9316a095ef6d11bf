"""`python -m fallkit.experiments <experiment dir> […]`: write (again) the report of existing runs."""

from __future__ import annotations

import argparse
import logging
import sys

from fallkit.errors import FallkitError
from fallkit.experiments.report import write_report


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m fallkit.experiments", description=__doc__)
    p.add_argument("dirs", nargs="+", help="experiment directories (experiments/<name>/<time>)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for d in args.dirs:
        try:
            write_report(d)
        except FallkitError as exc:
            print(f"fallkit: error: {exc}", file=sys.stderr)
            sys.exit(2)


if __name__ == "__main__":
    main()
