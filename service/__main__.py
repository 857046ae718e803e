"""`python -m service serve|scheduler|submit ...`: the service subcommands without the full
nprt CLI."""

import sys

from nprt.service.cli import OneLineParser
from nprt.service.cli_serve import add_serve_parsers


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="python -m service")
    add_serve_parsers(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
