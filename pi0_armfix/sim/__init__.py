"""The demo world as a simulator: world model and physics (`world`), cameras (`render`), the
scripted teleoperator (`expert`), the Gymnasium environment (`env`) and closed-loop rollouts
(`rollout`)."""
