"""``python -m volwarp_cli``: the ``volwarp`` command (how a batch runs each step)."""

from volwarp_cli.entry import main

if __name__ == "__main__":
    raise SystemExit(main())
