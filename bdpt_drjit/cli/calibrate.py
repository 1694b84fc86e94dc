"""``bdpt calibrate``: measure the unit costs of this machine and variant (units.py)."""
from __future__ import annotations

from .scene import setup_variant


def run(args, stop) -> int:
    setup_variant(args.variant)
    from ..render import calibrate
    from .. import units
    stop.check()
    measured = calibrate(args.repeats)
    print("bdpt: unit costs of %s (s): %s -> %s" % (args.variant, measured.describe(),
                                                    units.path()), flush=True)
    return 0
