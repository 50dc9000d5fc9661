"""Held-out evaluation of sampled action chunks: the metrics (`metrics`), the do-nothing
predictors every metric is shown beside (`baselines`), and the expert's own spread on the demo
(`ceiling`). The `Evaluator` that samples a run's policy lives in `pi0_armfix.evaluate`."""
