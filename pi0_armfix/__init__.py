"""pi0_armfix: per-group loss weighting for pi0 flow-matching policies against arm joint stagnation."""
