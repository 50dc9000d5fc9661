"""The policy as held-out evaluation calls it (`BatchPolicy`): the prediction function the
evaluator takes (`pi0_armfix.evaluation.evaluator.Evaluator`, as big_vision's evaluators take a
`predict_fn`), so that the evaluator knows the held-out chunks and how to score them, and nothing
of the model.

A batch of observations gives `eval.num_draws` draws per observation, each the mean of the levers'
draws (`Sampling.most_draws`, per group with `group_draws`), sampled by the run's sampler with the
noise of each held-out chunk drawn once (`noise`): a chunk's draws depend neither on the
evaluation batch size nor on which batch it lands in, and two evaluations differ only by the
params.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import numpy as np

from pi0_armfix import sharding as sharding_lib
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.model import flow_model
from pi0_armfix.policies.sampling import Sampling


class BatchPolicy:
    """`policy(params, observation, rows) -> [M, B, H, D]`: the normalized chunks of a batch of
    `B` observations (model batch keys, host arrays), `M` = `num_draws` each; `rows` are the
    held-out chunks the batch's first rows hold (their noise; the padding rows get zeros).

    Args:
      sampling: the policy's levers (`Sampling.for_run`), as a command executes them.
      model_config: the run's model.
      layout: the run's action layout (what `group_draws` names).
      num_draws: M, the draws scored per chunk (`eval.num_draws`).
      num_chunks: the held-out chunks, each with its own noise.
      seed: the noise's key (the run's seed).
      noise_factor: the correlated noise's Cholesky factor the run trains with, or None.
      mesh: the run's mesh; params_sharding: NamedShardings of the params.
    """

    def __init__(self, sampling: Sampling, model_config: model_config_lib.Pi0Config,
                 layout: ActionLayout, *, num_draws: int, num_chunks: int, seed: int,
                 noise_factor: np.ndarray | None, mesh: jax.sharding.Mesh,
                 params_sharding: Any):
        self.sampling = sampling
        self.draws, self.average = num_draws, sampling.most_draws
        self.draw_counts = sampling.draw_counts(layout)
        shape = (self.draws * self.average, num_chunks, model_config.action_horizon,
                 model_config.action_dim)
        self.noise = np.asarray(sampling.noise(
            jax.random.key(seed), (shape[0] * shape[1], *shape[2:]), noise_factor)
        ).reshape(shape)
        self.batch_sharding = sharding_lib.batch_sharding(mesh)
        sample = sampling.sampler(model_config, num_draws=shape[0])
        self._sample = jax.jit(
            lambda params, noise, observation: sample(params, None, observation, noise=noise),
            in_shardings=(params_sharding, None, self.batch_sharding),
            out_shardings=sharding_lib.replicated(mesh))

    def _global(self, x: np.ndarray) -> jax.Array:
        """This process's rows of a host batch `x` as a global array."""
        per_process = len(x) // jax.process_count()
        start = jax.process_index() * per_process
        return jax.make_array_from_process_local_data(self.batch_sharding,
                                                      x[start:start + per_process], x.shape)

    def __call__(self, params: Any, observation: Mapping[str, np.ndarray], rows: slice
                 ) -> np.ndarray:
        size = len(observation["state"])
        noise = np.zeros((len(self.noise), size, *self.noise.shape[2:]), np.float32)
        chunk_noise = self.noise[:, rows]
        noise[:, :chunk_noise.shape[1]] = chunk_noise
        draws = np.asarray(self._sample(params, noise.reshape(-1, *noise.shape[2:]),
                                        jax.tree.map(self._global, dict(observation))))
        draws = draws.reshape(self.draws, self.average, *draws.shape[1:]).swapaxes(0, 1)
        return np.asarray(flow_model.mean_of_draws(draws, self.draw_counts))
