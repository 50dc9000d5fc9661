"""Experiment configs (ml_collections): `--config=configs/<name>.py[:b1k]`. All share `base.py`."""
