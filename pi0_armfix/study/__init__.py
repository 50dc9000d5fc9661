"""Studies over configs and seeds: `python -m pi0_armfix.study` (`main`); the runs (`run`), their
numbers per config (`aggregate`) and the tables and figures (`report`)."""
