"""Held-out evaluation of sampled action chunks: the metrics (`metrics`), the do-nothing
predictors every metric is shown beside (`baselines`), and the expert's own spread on the demo
(`ceiling`), and the `Evaluator` that samples a run's policy on them (`evaluator`)."""
