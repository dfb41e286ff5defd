"""The command: compile the plant's numba kernel into its cache, as much as a command needs,
saying so (:mod:`pisc_plant.warm`)."""

from __future__ import annotations

import sys

from pisc_plant.warm import SCOPES, warm_up

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    scope = args[0] if args else "all"
    if scope not in SCOPES or len(args) > 1:
        print(f"usage: python -m pisc_plant.warm_cli [{'|'.join(SCOPES)}]", file=sys.stderr)
        return 2
    print(f"pisc_plant.warm: compiling the plant kernel for '{scope}' (minutes the first "
          "time, then loaded from numba's cache)", flush=True)
    total = warm_up(scope, lambda text: print(text, end="", flush=True))
    print(f"pisc_plant.warm: done in {total:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
