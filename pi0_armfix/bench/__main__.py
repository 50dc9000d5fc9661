"""Dispatches `python -m pi0_armfix.bench NAME [args]` to `pi0_armfix.bench.NAME.main(argv)`."""

import importlib
import sys

BENCHMARKS = ("data", "faults", "model", "serve", "sim", "step", "train", "video", "walltime")


USAGE = (f"usage: python -m pi0_armfix.bench {{{'|'.join(BENCHMARKS)}}} [flags]\n"
         "Each benchmark prints the numbers of one speed or memory target; "
         "`python -m pi0_armfix.bench NAME --help` lists its flags.")


def main(argv: list[str]) -> None:
    if len(argv) >= 2 and argv[1] in ("-h", "--help", "--helpfull"):
        print(USAGE)
        return
    if len(argv) < 2 or argv[1] not in BENCHMARKS:
        sys.exit(USAGE if len(argv) < 2 else f"pi0_armfix.bench: {argv[1]!r} is no benchmark; "
                 + USAGE)
    importlib.import_module(f"pi0_armfix.bench.{argv[1]}").main([argv[0]] + argv[2:])


def cli() -> None:
    """The `pi0-armfix-bench` console script."""
    main(sys.argv)


if __name__ == "__main__":
    cli()
