"""python -m onboard SUBCOMMAND: the drone's companion-computer node.

The node (video + MAVLink -> detector -> zenoh) lands with the Onboard issue; no subcommand exists yet.
"""

import argparse
import sys


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m onboard", description=__doc__)
    p.add_subparsers(dest="cmd", title="subcommands", metavar="(none yet)")
    args = p.parse_args(argv)
    if args.cmd is None:
        p.print_help()
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
