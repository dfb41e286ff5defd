"""The command: docs/parameters.md, generated from the parameter descriptors
(:mod:`pisc_bringup.param_docs`)."""

from __future__ import annotations

import sys

from pisc_bringup.param_docs import render

__all__ = ["main"]


def main() -> int:
    sys.stdout.write(render())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
