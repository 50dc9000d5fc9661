"""`python -m pi0_armfix.study`: the entry point of `pi0_armfix.study.main`."""

from pi0_armfix.study import main

__doc__ = main.__doc__  # absl's --help prints the __main__ module's docstring: the study's own
main.cli()
