"""Experiment configs (ml_collections): `--config=configs/<name>.py[:b1k]`. All share `base.py`.

The folder is the repository's `configs/`; the package reaches it as `pi0_armfix.configs` (the
link `pi0_armfix/configs`), so an installed copy ships the files inside `pi0_armfix` and
`--config=<name>` finds them from any folder, without a top-level package named `configs`."""
