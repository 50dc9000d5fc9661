"""Experiment configs (ml_collections), one file per experiment, all sharing `base.py`:
`--config=configs/<name>.py[:b1k]` or `--config=<name>`. A `--config` that names no file from
where the command runs is the config of that name here (`console.installed_config`), so the
README's commands work from the repository and from any folder of an installed copy."""
