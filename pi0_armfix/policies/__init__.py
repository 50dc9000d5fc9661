"""The policy: a trained run restored for inference (`inference`) and the grippers' hysteresis
(`hysteresis`)."""
