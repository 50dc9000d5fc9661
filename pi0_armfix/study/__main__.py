"""`python -m pi0_armfix.study`: see `pi0_armfix.study.main`."""

from pi0_armfix.study.main import cli

cli()
