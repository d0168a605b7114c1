"""python -m export SUBCOMMAND: train the apple detector and export it to ONNX (needs the `export` extra).

Training and export land with the Detector issue; no subcommand exists yet.
"""

import argparse
import sys


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m export", description=__doc__)
    p.add_subparsers(dest="cmd", title="subcommands", metavar="(none yet)")
    args = p.parse_args(argv)
    if args.cmd is None:
        p.print_help()
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
