"""Stagnation metrics of sampled action chunks against the recorded ones (docs/evaluation.md).

All functions take absolute action chunks in evaluation units (`evaluation_units`: data units
over a per-dim scale, not centred, so a zero velocity command stays 0). Per group g:

  err/<g>            MSE of the chunk against the true chunk.
  rms_units/<g>      its root in the data's own units (as the set stores them: radians or
                     degrees for a joint, m/s for a base): whether a negative skill is an arm
                     that jitters by a fraction of a degree or one that moves.
  skill/<g>          1 - err / err of holding the previous action (`baselines`); > 0: better than
                     doing nothing, 0: as good as doing nothing, 1: perfect.
  motion_gain/<g>    least-squares slope of predicted on true displacement; 1 = moves as far as
                     the data in the data's direction, 0 = stagnation (or motion unrelated to the
                     data's).
  motion_ratio/<g>   ratio of displacement magnitudes (inflated by sampling noise: a policy that
                     moves as much as the data in unrelated directions scores 1 here, 0 in gain).
  gripper_switch/{precision,recall,f1,tp,fp,fn}
                     open/close switch events: a predicted switch matches a true one of the same
                     direction and dim within `switch_tolerance` steps, each used once.
  energy/<g>         energy score of N draws of a chunk (`energy_sums`): E|X - y| - E|X - X'|/2
                     over the group's dims and valid steps, mean over chunks; a proper scoring
                     rule (lower is better) that rewards neither a spread-free bias nor noise.
  energy_skill/<g>   1 - energy / persistence's energy (a point prediction's energy score is its
                     error norm): the sampler against doing nothing, spread counted fairly.

A flow policy is a sampler: a single draw's error is its bias^2 plus its own spread, while
persistence is a point prediction. The evaluation reports the single draw (what a robot executes)
under the plain keys, the mean of N draws under `mean_of_draws/...` (the spread averaged away)
and the energy score over the N draws.

A displacement is the chunk's last valid action minus its first (the current one); for a velocity
group (`ActionLayout.velocity_groups`, the B1K base) it is the chunk's mean command measured from
the zero command (a standing base is 0). A gripper switch is a crossing of the dim's open/close
boundary (`action_space.gripper_boundary`) between two consecutive valid steps.

Every metric is a ratio of sums over chunks (`chunk_sums`, one row per chunk), so the metrics of
any multiset of chunks (a resample of the held-out episodes, `metrics_from_sums`) come from the
per-chunk sums without sampling again: the study's intervals take the held-out episodes'
sampling error from them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pi0_armfix.action_space import ActionLayout, gripper_boundary
from pi0_armfix.data.pipeline import transforms
from pi0_armfix.data.statistics import stats as stats_lib


def _last_valid(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """`x[n, last valid h]` -> `[N, D]` (the tail of a chunk at an episode end is padding)."""
    last = np.maximum(valid.sum(axis=1) - 1, 0)
    return x[np.arange(len(x)), last]


def displacement(chunk: np.ndarray, valid: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """How far a chunk moves, `[N, D]`: last valid action minus the first (the current one) on
    position dims; the mean over the valid steps on velocity dims, measured from the zero command.

    Args:
      chunk: `[N, H, D]` in units whose 0 is the zero command; valid: `[N, H]` bool;
        velocity: `[D]` bool.
    """
    position = _last_valid(chunk, valid) - chunk[:, 0]
    w = valid[..., None].astype(chunk.dtype)
    mean = (chunk * w).sum(axis=1) / np.maximum(w.sum(axis=1), 1.0)
    return np.where(velocity, mean, position)


def switch_events(chunk: np.ndarray, valid: np.ndarray, threshold: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The gripper switches of chunks: crossings of `threshold` between two consecutive valid steps.

    Args:
      chunk: `[N, H, D]`; valid: `[N, H]` bool; threshold: `[D]` the open/close boundary.
    Returns:
      `(up, down)`, each `[N, D, H]` bool: True at step h when the dim crosses upwards (opens) /
      downwards (closes) between steps h - 1 and h (h = 0 is always False).
    """
    above = chunk > threshold
    both_valid = (valid[:, 1:] & valid[:, :-1])[..., None]
    up = ~above[:, :-1] & above[:, 1:] & both_valid
    down = above[:, :-1] & ~above[:, 1:] & both_valid
    start = np.zeros_like(up[:, :1])
    return tuple(np.concatenate([start, x], axis=1).transpose(0, 2, 1) for x in (up, down))


def matched_events(predicted: np.ndarray, true: np.ndarray, tolerance: int) -> np.ndarray:
    """The true switch events matched one-to-one by a predicted event of the same kind within
    `tolerance` steps (greedy in time order, each predicted event used once).

    Args:
      predicted, true: `[R, H]` bool events (one row per chunk, dim and direction).
    Returns:
      `[R, H]` bool: the matched true events.
    """
    matched = np.zeros(np.shape(true), bool)
    for row, true_row in enumerate(true):
        candidates = list(np.flatnonzero(predicted[row]))
        for h in np.flatnonzero(true_row):
            near = [p for p in candidates if abs(p - h) <= tolerance]
            if near:
                candidates.remove(min(near, key=lambda p: abs(p - h)))
                matched[row, h] = True
    return matched


def matched_switches(predicted: np.ndarray, true: np.ndarray, tolerance: int) -> np.ndarray:
    """`[R]` per row, the count of `matched_events`."""
    return matched_events(predicted, true, tolerance).sum(axis=-1)


def switch_sums(predicted: np.ndarray, true: np.ndarray, valid: np.ndarray,
                threshold: np.ndarray, tolerance: int) -> dict[str, np.ndarray]:
    """Per chunk `[N]`, the gripper switch events: matched (`switch/tp`), predicted
    (`switch/predicted`) and true (`switch/true`).

    Args:
      predicted, true: `[N, H, D]` gripper dims; valid: `[N, H]`; threshold: `[D]`.
    """
    pred_events = np.stack(switch_events(predicted, valid, threshold), axis=1)  # [N, 2, D, H]
    true_events = np.stack(switch_events(true, valid, threshold), axis=1)
    n, horizon = len(predicted), predicted.shape[1]
    tp = matched_switches(pred_events.reshape(-1, horizon), true_events.reshape(-1, horizon),
                          tolerance).reshape(n, -1).sum(axis=1)
    return {"switch/tp": tp.astype(np.float64),
            "switch/predicted": pred_events.reshape(n, -1).sum(axis=1).astype(np.float64),
            "switch/true": true_events.reshape(n, -1).sum(axis=1).astype(np.float64)}


def switch_scores(sums: dict[str, float]) -> dict[str, float]:
    """Precision, recall and F1 of the predicted gripper switches against the true ones, and the
    event counts behind them (`tp`, `fp`, `fn`), from summed `switch_sums`.

    Each event is counted once when the chunks do not overlap on the episode timeline (the
    `Evaluator`'s chunks tile the held-out episodes). Precision is NaN without any predicted
    switch, recall without any true switch, F1 (`2 TP / (2 TP + FP + FN)`) without either.
    """
    tp, num_pred, num_true = sums["switch/tp"], sums["switch/predicted"], sums["switch/true"]

    def ratio(num, den):
        return float(num / den) if den else float("nan")

    return {"gripper_switch/precision": ratio(tp, num_pred),
            "gripper_switch/recall": ratio(tp, num_true),
            "gripper_switch/f1": ratio(2 * tp, num_pred + num_true),
            "gripper_switch/tp": float(tp), "gripper_switch/fp": float(num_pred - tp),
            "gripper_switch/fn": float(num_true - tp)}


def chunk_sums(predicted: np.ndarray, true: np.ndarray, valid: np.ndarray, *,
               layout: ActionLayout, gripper_groups: Sequence[str],
               gripper_threshold: np.ndarray, switch_tolerance: int = 2,
               scale: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Per chunk, the sums every metric is a ratio of (`metrics_from_sums`), float64 `[N]` each.

    Args:
      predicted, true: `[N, H, D]` absolute action chunks in evaluation units (D >= real_dim).
      valid: `[N, H]` bool, False on the padded tail of a chunk at an episode end.
      gripper_groups: groups whose dims are open/close commands.
      gripper_threshold: `[D]` the open/close boundary of each dim, same units.
      switch_tolerance: steps by which a predicted gripper switch may miss the true one.
      scale: `[D]` the evaluation units' per-dim scale (`evaluation_units`); given, the squared
        error in the data's units is summed too (`sq_err_units/<g>`).
    Returns:
      per group g `sq_err/<g>` and `steps/<g>` (valid steps x dims), `motion_dot/<g>` (predicted
      . true displacement), `motion_true/<g>` (|true displacement|^2), `norm_predicted/<g>` and
      `norm_true/<g>` (displacement lengths); `switch/{tp,predicted,true}` (`switch_sums`).
    """
    predicted, true = np.asarray(predicted, np.float64), np.asarray(true, np.float64)
    velocity = transforms.pad_last(layout.velocity_mask()[:layout.real_dim], true.shape[-1])
    dp = displacement(predicted, valid, velocity)
    dt = displacement(true, valid, velocity)
    sq_err = np.square(predicted - true)
    w = valid[..., None].astype(np.float64)
    sums = {}
    for g in layout.group_names:
        dims = layout.group_dims(g)
        sums[f"sq_err/{g}"] = (sq_err[..., dims] * w).sum(axis=(1, 2))
        if scale is not None:
            units = np.square(np.asarray(scale, np.float64)[dims])
            sums[f"sq_err_units/{g}"] = (sq_err[..., dims] * units * w).sum(axis=(1, 2))
        sums[f"steps/{g}"] = w.sum(axis=(1, 2)) * len(dims)
        sums[f"motion_dot/{g}"] = np.sum(dp[:, dims] * dt[:, dims], axis=1)
        sums[f"motion_true/{g}"] = np.sum(dt[:, dims] ** 2, axis=1)
        sums[f"norm_predicted/{g}"] = np.linalg.norm(dp[:, dims], axis=-1)
        sums[f"norm_true/{g}"] = np.linalg.norm(dt[:, dims], axis=-1)
    dims = np.concatenate([layout.group_dims(g) for g in gripper_groups] + [np.zeros(0, int)])
    sums.update(switch_sums(predicted[..., dims], true[..., dims], valid,
                            np.asarray(gripper_threshold)[dims], switch_tolerance))
    return sums


def energy_sums(draws: np.ndarray, true: np.ndarray, valid: np.ndarray, *,
                layout: ActionLayout) -> dict[str, np.ndarray]:
    """Per chunk `[N]`, each group's energy score over `draws` and the chunk count
    (`energy_chunks`, 1 each).

    ES = (1/M) sum_m |X_m - y| - 1/(2 M (M - 1)) sum_{m != m'} |X_m - X_m'|, the unbiased ("fair")
    estimator, with X_m the group's dims over the chunk's valid steps, flattened, `|.|` the
    Euclidean norm; for M = 1 (a point prediction) the second term is 0.

    Args:
      draws: `[M, N, H, D]` sampled chunks; true: `[N, H, D]`; valid: `[N, H]` bool.
    """
    draws, true = np.asarray(draws, np.float64), np.asarray(true, np.float64)
    num_draws = len(draws)
    w = valid[..., None].astype(np.float64)
    sums = {"energy_chunks": np.ones(len(true))}
    for g in layout.group_names:
        dims = layout.group_dims(g)
        x = (draws[..., dims] * w).reshape(num_draws, len(true), -1)  # [M, N, K]
        y = (true[..., dims] * w).reshape(len(true), -1)
        accuracy = np.linalg.norm(x - y, axis=-1).mean(axis=0)
        spread = np.zeros(len(true))
        if num_draws > 1:
            pairwise = np.linalg.norm(x[:, None] - x[None], axis=-1).sum(axis=(0, 1))
            spread = pairwise / (2 * num_draws * (num_draws - 1))
        sums[f"energy/{g}"] = accuracy - spread
    return sums


def energy_scores(sums: dict[str, float], layout: ActionLayout) -> dict[str, float]:
    """`energy/<g>`, the mean energy score over chunks, from summed `energy_sums`."""
    chunks = sums["energy_chunks"]
    return {f"energy/{g}": float(sums[f"energy/{g}"] / chunks) if chunks else float("nan")
            for g in layout.group_names}


def metrics_from_sums(sums: dict[str, float], layout: ActionLayout) -> dict[str, float]:
    """The metrics (module docstring) of chunks whose `chunk_sums` add up to `sums`: `err/<g>`,
    `motion_gain/<g>`, `motion_ratio/<g>` for every group and
    `gripper_switch/{precision,recall,f1,tp,fp,fn}`, and `energy/<g>` where `sums` hold
    `energy_sums`; NaN where the data gives nothing to measure."""
    metrics = {}
    for g in layout.group_names:
        metrics[f"err/{g}"] = float(sums[f"sq_err/{g}"] / max(sums[f"steps/{g}"], 1.0))
        if f"sq_err_units/{g}" in sums:
            metrics[f"rms_units/{g}"] = float(np.sqrt(sums[f"sq_err_units/{g}"]
                                                      / max(sums[f"steps/{g}"], 1.0)))
        true_motion = sums[f"motion_true/{g}"]
        metrics[f"motion_gain/{g}"] = (float(sums[f"motion_dot/{g}"] / true_motion)
                                       if true_motion > 0 else float("nan"))
        true_norm = sums[f"norm_true/{g}"]
        metrics[f"motion_ratio/{g}"] = (float(sums[f"norm_predicted/{g}"] / true_norm)
                                        if true_norm > 0 else float("nan"))
    metrics.update(switch_scores(sums))
    if "energy_chunks" in sums:
        metrics.update(energy_scores(sums, layout))
    return metrics


def chunk_metrics(predicted: np.ndarray, true: np.ndarray, valid: np.ndarray, *,
                  layout: ActionLayout, gripper_groups: Sequence[str],
                  gripper_threshold: np.ndarray, switch_tolerance: int = 2) -> dict[str, float]:
    """Stagnation metrics of sampled chunks against the true ones (see the module docstring):
    `metrics_from_sums` of all the chunks' `chunk_sums` (same arguments). Computed in float64."""
    sums = chunk_sums(predicted, true, valid, layout=layout, gripper_groups=gripper_groups,
                      gripper_threshold=gripper_threshold, switch_tolerance=switch_tolerance)
    return metrics_from_sums({k: float(v.sum()) for k, v in sums.items()}, layout)


def skill_scores(metrics: dict[str, float], persistence: dict[str, float],
                 layout: ActionLayout) -> dict[str, float]:
    """`skill/<g> = 1 - err/<g> / persistence's err/<g>` (NaN where persistence is exact), and
    `energy_skill/<g>` likewise from `energy/<g>` where both have it."""
    skills = {}
    for g in layout.group_names:
        for score, skill in (("err", "skill"), ("energy", "energy_skill")):
            if f"{score}/{g}" not in metrics or f"{score}/{g}" not in persistence:
                continue
            reference = persistence[f"{score}/{g}"]
            skills[f"{skill}/{g}"] = (1.0 - metrics[f"{score}/{g}"] / reference if reference > 0
                                      else float("nan"))
    return skills


def evaluation_units(std: np.ndarray, q01: np.ndarray, q99: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The common units of every run's metrics, from absolute-action statistics in data units
    (the training split's, `norm_stats.json`'s `actions_absolute`).

    Runs differ in normalization (z-score, quantile, balanced, per timestep) and in action
    representation (absolute or delta), so their normalized units cannot be compared. Metrics are
    taken on absolute actions in data units divided by each dim's std; a constant dim
    (`NormStats.constant`) is measured in data units, never blown up; not centred,
    so a zero velocity command stays 0. Float64.

    Args:
      std, q01, q99: `[D]` per-dim statistics of the absolute actions, data units.
    Returns:
      `(scale [D], gripper threshold [D])`: divide by `scale`; the threshold
      (`gripper_boundary`) is in the divided units.
    """
    std = np.asarray(std, np.float64)
    scale = np.where(std < stats_lib.CONSTANT_SPREAD, 1.0, std)
    q01, q99 = np.asarray(q01, np.float64), np.asarray(q99, np.float64)
    return scale, gripper_boundary(q01, q99) / scale
