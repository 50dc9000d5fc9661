"""A checkpoint's policy driving the demo world (`pi0_armfix.sim`): `evaluate --closed_loop`.

    python -m pi0_armfix.evaluate --workdir=RUN --closed_loop [--episodes=50] [--n_exec=K] [--rtc]
        [--temporal_ensemble=M] [--deadband=base=0.2] [--group_draws=base=4] \
        [--gripper_hysteresis=0.9,-0.98] [--tolerances=1,2,4] [--sim_seed=S]

The policy samples a chunk, the world executes `n_exec` of it, the policy replans, with the run's
execution levers or the command's (`policies.execution.Replanner`); the rollouts (`sim.rollout`)
record every phase's success and, for a failed
phase, the furthest stage it reached (its failure reason). What a success means physically:
docs/evaluation.md. Results are named by their settings (`closed_loop_paths`), never replaced by
another evaluation's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import jax
from etils import epath

from pi0_armfix.policies import execution, inference, restore
from pi0_armfix.data import json_files
from pi0_armfix.evaluation.outputs import strict_json, writable_folder
from pi0_armfix.sim import env as env_lib
from pi0_armfix.sim import rollout as rollout_lib
from pi0_armfix.sim.world import DemoSpec
from pi0_armfix import wall_time

CLOSED_LOOP_STEM = "closed_loop"  # a closed-loop evaluation's files (`closed_loop_paths`)
ROLLOUT_ROWS = 3  # episodes shown in the rollout figure


def closed_loop(workdir: epath.PathLike, step: int | None = None, params_name: str = "ema", *,
                episodes: int = 50, sim_seed: int = env_lib.EVAL_SEED, progress: bool = True,
                tolerances: Sequence[float] = (), levers: Mapping[str, Any] | None = None
                ) -> tuple[int, dict[str, Any]]:
    """Runs a checkpoint's policy in the demo world (`pi0_armfix.sim`) on `episodes` episodes of
    world seed `sim_seed`, sampled and executed with the run's levers (`policies.sampling.
    Sampling`, `policies.execution.Replanner`; `levers`: a command's in their place,
    `restore.restore_run`); writes `closed_loop_<episodes>ep[...].json` and
    `rollouts_<episodes>ep[...].png` (against the scripted expert; `closed_loop_paths`: named by
    their settings, so no other evaluation replaces them) into `<workdir>/eval/step_<N>/`. With
    `tolerances` (factors other than 1), the same episodes again in the world with its success
    tolerances times each factor: `success_curve` in the summary, `success_curve.png`. Returns
    `(step, summary)` (`sim.rollout.summarize`)."""
    if episodes < 1:
        raise ValueError(f"--episodes = {episodes} must be >= 1")
    if sim_seed < 0:
        raise ValueError(f"--sim_seed = {sim_seed} must be >= 0 (a world seed)")
    if any(f <= 0 for f in tolerances):
        raise ValueError(f"--tolerances={list(tolerances)} must be factors > 0")
    wall = wall_time.WallTime()
    with wall.part("restore the run"):
        policy_ = inference.RunPolicy(restore.restore_run(workdir, step, params_name, levers))
    run, sampling = policy_.run, policy_.sampling
    replanning = execution.Replanner(policy_)  # its levers checked before any rollout
    n_exec = replanning.n_exec
    tag = run.result_tag(closed_loop=True)
    results_path, figure_path = closed_loop_paths(run.workdir, run.step, episodes=episodes,
                                                  sim_seed=sim_seed, levers=tag)
    writable_folder(results_path.parent)  # before the rollouts, not after
    if run.layout.real_dim != 23:
        raise ValueError(f"the run's actions have {run.layout.real_dim} dims; the demo world "
                         "takes the 23-D B1K action (layout b1k_r1pro)")
    spec = DemoSpec(seed=sim_seed)
    with wall.part(f"{episodes} episodes (the first replan compiles)"):
        records = rollout_lib.rollout(replanning, range(episodes), spec=spec, n_exec=n_exec,
                                      progress=progress and jax.process_index() == 0)
    summary = {"step": run.step, "params": run.params_name, "sim_seed": sim_seed,
               **sampling.describe(), "n_exec": n_exec,
               "results": str(results_path), "figure": str(figure_path),
               **rollout_lib.summarize(records),
               "episodes_detail": rollout_lib.episode_details(records)}
    looser = [f for f in tolerances if f != 1]
    if looser:
        summary["success_curve"] = {"1": {k: v for k, v in summary.items()
                                          if k.startswith(("success/", "phase_success/"))}}
        with wall.part(f"{episodes} episodes x {len(looser)} looser tolerances"):
            curve = rollout_lib.success_curve(
                replanning, range(episodes), spec=spec, factors=looser, n_exec=n_exec,
                progress=progress and jax.process_index() == 0)
        summary["success_curve"] |= {
            factor: {k: v for k, v in measured.items()
                     if k.startswith(("success/", "phase_success/")) or k == "episodes_detail"}
            for factor, measured in curve.items()}
    json_files.write_json_atomic(results_path, strict_json(summary))
    wall.save(wall_time_path(results_path))
    if looser:
        rollout_lib.plot_success_curves({"policy": summary["success_curve"]},
                                        figure_path.with_name(
                                            figure_path.name.replace("rollouts", "success_curve")),
                                        f"step {run.step}: {episodes} episodes")
    shown = records[:ROLLOUT_ROWS]
    expert = rollout_lib.rollout(rollout_lib.ExpertDriver(), [r.episode for r in shown],
                                 spec=spec, progress=False)
    rollout_lib.plot_rollouts(shown, expert, figure_path,
                              f"step {run.step}: closed loop, n_exec {n_exec}"
                              + (f", levers {tag}" if tag else ""))
    return run.step, summary


def wall_time_path(results_path: epath.Path) -> epath.Path:
    """Where a closed-loop evaluation's seconds by part go: beside its results, named alike."""
    return results_path.with_name(results_path.stem + "." + wall_time.FILE)


def closed_loop_paths(workdir: epath.PathLike, step: int, *, episodes: int,
                      sim_seed: int = env_lib.EVAL_SEED, levers: str = ""
                      ) -> tuple[epath.Path, epath.Path]:
    """`eval/step_<N>/closed_loop_<E>ep[_seed<S>][levers].json` and the `rollouts_...png` beside
    it: named by the settings that change the result (the world seed when not the evaluation's;
    `levers`: `RestoredRun.result_tag(closed_loop=True)` of the run read: its sampling and
    execution levers, and the raw params of a run with an EMA)."""
    out = epath.Path(workdir) / "eval" / f"step_{step}"
    tag = (f"_{episodes}ep" + (f"_seed{sim_seed}" if sim_seed != env_lib.EVAL_SEED else "")
           + levers)
    return out / f"{CLOSED_LOOP_STEM}{tag}.json", out / f"rollouts{tag}.png"
