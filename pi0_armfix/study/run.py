"""Running a study's runs: one training subprocess per (config, seed) in its run folder, resumed
where interrupted, then its held-out episode replicates and its closed loop, each kept in the run's
`result.json` (the study's entry point and its outputs: `pi0_armfix.study`)."""

from __future__ import annotations

import concurrent.futures
import contextlib
import functools
import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data import json_files
from pi0_armfix.evaluation import closed_loop as closed_loop_lib
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.evaluation import chunk_sums as chunk_sums_lib
from pi0_armfix.study.aggregate import (CLOSED_LOOP, CLOSED_LOOP_EPISODES,
                                        CLOSED_LOOP_TOLERANCES, EPISODE_REPLICATES,
                                        LOOSER_TOLERANCES, closed_loop_outcomes, curve_prefix,
                                        episode_replicates, group_keys, has_outcomes)
from pi0_armfix.policies.sampling import LEVERS, SAMPLED_LEVERS, Sampling, check_levers
from pi0_armfix.training import metrics_log

RESULT_FILE = "result.json"
# A demo-world episode of the closed loop on 2 cores (the main job's policy at 6000 steps: 20
# episodes x 3 tolerances in 175 s, the test suite sharing the cores): the estimate announced.
CLOSED_LOOP_SECONDS = 3.0
CLOSED_LOOP_STEPS_PER_EPISODE = 120  # the default closed loop: one episode per this many steps



def run_folder(workdir: Path, config: str, seed: int) -> Path:
    return workdir / config.replace(":", "_").replace("/", "_") / f"seed_{seed}"


def parse_config(config: str) -> tuple[str, str, list[str]]:
    """A study's config name -> (file name of pi0_armfix/configs/, its argument ('' for none),
    overrides of
    its own): `arm_focused`, `arm_focused:b1k`, `arm_focused@data.video_access=random` (every
    `@key=value` is passed to this config's runs only)."""
    head, *overrides = config.split("@")
    name, _, arg = head.partition(":")
    return name, arg, overrides


def config_names(parts: Sequence[str], known: Sequence[str] = ()) -> list[str]:
    """`--configs` as absl splits it, at every comma -> the study's configs: a part that cannot
    begin a config name (`-0.98`, `0.5`), or that names no config of `known` (the installed
    ones) right after an override's value, continues the one before it, so a lever whose value
    is a list (`arm_focused@eval.gripper_hysteresis=0.9,-0.98`,
    `arm_focused@eval.gripper_groups=left_gripper,right_gripper`) stays one config."""
    configs: list[str] = []
    for part in filter(None, parts):
        name = part.partition("@")[0].partition(":")[0]
        in_a_value = bool(configs) and "=" in configs[-1].rpartition("@")[2]
        if configs and (not (part[0].isalpha() or part[0] == "_")
                        or (in_a_value and "@" not in part and known and name not in known)):
            configs[-1] += f",{part}"
        else:
            configs.append(part)
    return configs


def inference_levers(config: str) -> dict[str, str]:
    """A study config's own inference levers: its `@eval.<lever>=<value>` overrides of
    `sampling.LEVERS` and `@eval.execution` (`{"average_draws": "4"}`), the rest of its
    overrides left out."""
    own = (o.partition("=")[::2] for o in parse_config(config)[2])
    return {key.removeprefix("eval."): value for key, value in own
            if key.startswith("eval.") and key.removeprefix("eval.") in ("execution", *LEVERS)}


def check_study_levers(configs: Sequence[str], execution: str = "adopted") -> None:
    """Refuses, before any run trains, the study's `execution` or a lever variant whose levers
    are out of range.

    Raises:
      ValueError naming the config and the lever's range.
    """
    check_levers({"execution": execution})
    for config in configs:
        try:
            check_levers({"execution": execution, **inference_levers(config)})
        except ValueError as err:
            raise ValueError(f"--configs {config}: {err}") from None


def saved_config(folder: Path) -> dict[str, Any]:
    """A trained run's config as it saved it (`config.json` of its folder)."""
    return json.loads((folder / "config.json").read_text())


def run_execution(saved: Mapping[str, Any], config: str) -> Sampling:
    """How a study config is executed on its trained run (`saved`: that run's `saved_config`):
    the run's own execution (`Sampling.for_run`; the study's `--execution` set it alike for every
    config) with the config's levers in place."""
    return Sampling.for_run(saved, **inference_levers(config))


def trained_config(config: str) -> str:
    """The config whose runs train `config`'s checkpoints: `config` less its inference levers.
    A lever changes how a checkpoint is sampled, not what is trained, so a lever variant
    (`arm_focused@eval.average_draws=4`) trains nothing: it is measured on its trained config's
    checkpoints, seed for seed, and what differs between the two is the lever alone."""
    levers = {f"eval.{k}={v}" for k, v in inference_levers(config).items()}
    return "@".join(part for part in config.split("@") if part not in levers)


def lever_args(config: str) -> list[str]:
    """`pi0_armfix.evaluate`'s flags for a config's inference levers (none for a trained
    config)."""
    return [f"--{key}={value}" for key, value in inference_levers(config).items()]


def lever_tag(config: str, checkpoints: Path, closed_loop: bool = False) -> str:
    """`Sampling.tag` of a config's levers on its trained run (that run's `eval` with the
    config's levers in place, against the run's own): the tag of the evaluation files its levers
    write (held-out, or `closed_loop`)."""
    saved = saved_config(checkpoints)
    return run_execution(saved, config).tag(closed_loop, against=Sampling.for_run(saved))


def run_steps(config: str, steps: int) -> int:
    """The steps a config's runs train: its own `@train.total_steps=N` where it names one (a
    recipe whose steps cost differently, compared at equal wall time), else the study's
    `steps`."""
    own = dict(o.partition("=")[::2] for o in parse_config(config)[2])
    return int(own.get("train.total_steps", steps))


def train_command(config: str, seed: int, steps: int, folder: Path,
                  overrides: Sequence[str], evaluations: int = 1) -> list[str]:
    """The `pi0_armfix.train` command line of one run (`overrides`: the study's, then the
    config's own), with `evaluations` held-out evaluations spread over its steps, the last at
    its end (the learning curve; `eval.evaluations`)."""
    name, arg, own = parse_config(config)
    return [sys.executable, "-m", "pi0_armfix.train",
            f"--config=configs/{name}.py" + (f":{arg}" if arg else ""),
            f"--workdir={folder}", f"--config.seed={seed}",
            f"--config.train.total_steps={steps}",
            f"--config.eval.evaluations={evaluations}",
            *[f"--config.{o}" for o in [*overrides, *own]]]


def closed_loop_plan(runs: int, episodes: int) -> str:
    """One line: what the study's closed loop will cost (episodes x tolerances x runs, and the
    time at `CLOSED_LOOP_SECONDS` per episode)."""
    rollouts = runs * episodes * len(CLOSED_LOOP_TOLERANCES)
    minutes = rollouts * CLOSED_LOOP_SECONDS / 60
    return (f"study: closed loop: {episodes} episodes x {len(CLOSED_LOOP_TOLERANCES)} tolerances "
            f"x {runs} runs = {rollouts} episodes of the demo world, ~{minutes:.0f} min on 2 "
            f"cores (~{CLOSED_LOOP_SECONDS:g} s each); --closed_loop_episodes=0 skips them")


def default_closed_loop_episodes(steps: int) -> int:
    """The closed loop in proportion to the training budget: one episode per
    `CLOSED_LOOP_STEPS_PER_EPISODE` training steps, within [10, 50]."""
    return int(min(50, max(10, round(steps / CLOSED_LOOP_STEPS_PER_EPISODE))))


def final_evaluation(folder: Path) -> dict[str, float]:
    """The last held-out evaluation record of a run's `metrics.jsonl`."""
    records = [r for r in metrics_log.read_metrics(folder / metrics_log.METRICS_FILE)
               if any(k.startswith("motion_gain/") for k in r)]
    if not records:
        raise ValueError(f"{folder} has no held-out evaluation in {metrics_log.METRICS_FILE}; "
                         f"see {folder / 'train.log'}")
    return records[-1]


class StudyInterrupted(Exception):
    """The study was asked to stop (SIGINT or SIGTERM)."""


class Children:
    """The study's child processes (training, evaluation), each in its own process group so that
    a Ctrl-C reaches the study alone, which then stops them (SIGTERM: a training run saves a
    checkpoint and exits) and starts no other: nothing is left running, nothing is lost."""

    def __init__(self):
        self._lock = threading.Lock()
        self._running: set[subprocess.Popen] = set()
        self.stopping = threading.Event()

    def run(self, command: list[str], log) -> int:
        with self._lock:
            if self.stopping.is_set():
                raise StudyInterrupted()
            child = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                                     env=os.environ, start_new_session=True)
            self._running.add(child)
        try:
            code = child.wait()
        finally:
            with self._lock:
                self._running.discard(child)
        if self.stopping.is_set():
            raise StudyInterrupted()
        return code

    def stop(self, *_) -> None:
        """Starts no more children and sends SIGTERM to the running ones' process groups."""
        with self._lock:
            self.stopping.set()
            for child in self._running:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(child.pid, signal.SIGTERM)


CHILDREN = Children()


def _logged(command: list[str], folder: Path, what: str) -> None:
    """Runs `command`, its output appended to the run's `train.log`; raises on failure
    (`StudyInterrupted` when the study is stopping)."""
    with open(folder / "train.log", "a") as log:
        returncode = CHILDREN.run(command, log)
    if returncode:
        tail = (folder / "train.log").read_text().splitlines()[-5:]
        raise RuntimeError(f"{what} failed (exit {returncode}); the end of "
                           f"{folder / 'train.log'}:\n" + "\n".join(tail))


def closed_loop_metrics(workdir: Path, config: str, seed: int, steps: int, episodes: int
                        ) -> tuple[dict[str, float], dict[str, list[int]]]:
    """Runs the closed-loop evaluation of a run's step `steps` (`pi0_armfix.evaluate
    --closed_loop` on its trained run's checkpoint with the config's inference levers, with the
    success curve at `CLOSED_LOOP_TOLERANCES`) and returns its rates as `closed_loop/<name>`
    metrics (the curve's as `closed_loop/curve/<f>x/<name>`) and the per-episode outcomes
    (`aggregate.closed_loop_outcomes`)."""
    folder = run_folder(workdir, config, seed)
    checkpoints = run_folder(workdir, trained_config(config), seed)
    factors = ",".join(f"{f:g}" for f in CLOSED_LOOP_TOLERANCES)
    _logged([sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={checkpoints}",
             f"--step={steps}", "--closed_loop", f"--episodes={episodes}",
             f"--tolerances={factors}", *lever_args(config)], folder,
            f"the closed-loop evaluation of {folder}")
    path, _ = closed_loop_lib.closed_loop_paths(
        checkpoints, steps, episodes=episodes, levers=lever_tag(config, checkpoints, True))
    saved = json.loads(path.read_text())
    metrics = {CLOSED_LOOP + k: v for k, v in saved.items()
               if k.startswith(("success/", "phase_success/", "progress/", "failure/",
                                "gripper_switches/", "seconds_to"))
               or k == "episodes"}
    outcomes = closed_loop_outcomes(saved["episodes_detail"])
    for factor, rates in saved.get("success_curve", {}).items():
        at = curve_prefix(float(factor))
        metrics |= {CLOSED_LOOP + at + k: v for k, v in rates.items()
                    if k.startswith(("success/", "phase_success/"))}
        if "episodes_detail" in rates:
            outcomes |= {at + k: v for k, v in
                         closed_loop_outcomes(rates["episodes_detail"]).items()}
    return metrics, outcomes


def add_episode_replicates(result: dict[str, Any], folder: Path, evaluate_missing: bool
                           ) -> dict[str, Any]:
    """The result with its `episode_replicates` (`result.json` rewritten), from the run's
    per-chunk sums; a run without them is evaluated again from its checkpoint when
    `evaluate_missing`, else (or without a checkpoint) returned as it is. Replicates kept before
    the per-group ones (`aggregate.group_keys`) are recomputed where the sums are kept."""
    kept = result.get(EPISODE_REPLICATES)
    path = evaluator_lib.heldout_paths(folder, result["steps"])[1]
    if not path.exists():
        if kept is not None or not evaluate_missing or not (folder / "checkpoints").is_dir():
            return result
        _logged([sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={folder}",
                 f"--step={result['steps']}"], folder, f"the held-out evaluation of {folder}")
    layout = ActionLayout.from_config(result["layout"])
    if kept is not None and all(k in kept for k in group_keys(layout)):
        return result
    result = {**result, EPISODE_REPLICATES: episode_replicates(
        chunk_sums_lib.load_chunk_sums(path), layout)}
    json_files.write_json_atomic(folder / RESULT_FILE, result)
    return result


def run_one(config: str, seed: int, steps: int, workdir: Path, overrides: Sequence[str],
            closed_loop_episodes: int = 0, evaluations: int = 1) -> dict[str, Any]:
    """Trains (or resumes) one run, evaluates it in closed loop when asked, and writes its
    `result.json`; returns the result. A lever variant trains nothing (`measure_levers`)."""
    folder = run_folder(workdir, config, seed)
    folder.mkdir(parents=True, exist_ok=True)
    if trained_config(config) != config:
        return add_closed_loop(measure_levers(config, seed, workdir), workdir,
                               closed_loop_episodes)
    _logged(train_command(config, seed, steps, folder, overrides, evaluations), folder,
            f"{config} seed {seed}")
    evaluation, trained = final_evaluation(folder), run_steps(config, steps)
    if evaluation["step"] != trained:
        raise RuntimeError(f"{folder}: the last evaluation is of step {evaluation['step']}, "
                           f"not {trained}")
    saved = saved_config(folder)
    result = {"config": config, "seed": seed, "steps": trained, "layout": saved["layout"],
              "execution": run_execution(saved, config).summary(),
              "metrics": {k: v for k, v in evaluation.items() if k != "step"}}
    json_files.write_json_atomic(folder / RESULT_FILE, result)
    result = add_episode_replicates(result, folder, evaluate_missing=True)
    return add_closed_loop(result, workdir, closed_loop_episodes)


def measure_levers(config: str, seed: int, workdir: Path) -> dict[str, Any]:
    """A lever variant's result: the final checkpoint of its trained config's run of the same
    seed (finished) evaluated on the held-out chunks with the variant's sampled levers
    (`pi0_armfix.evaluate --average_draws=...`, files tagged by the levers in that run's
    `eval/step_<N>/`; a variant of execution levers alone samples the trained config's chunks and
    takes its held-out metrics), with its episode replicates; `result.json` written in the
    variant's own folder, which holds the evaluations' log."""
    folder, trained = run_folder(workdir, config, seed), trained_config(config)
    checkpoints = run_folder(workdir, trained, seed)
    base = load_result(checkpoints)
    if base is None:
        raise RuntimeError(f"{config} seed {seed} is measured on the checkpoints of {trained} "
                           f"seed {seed}, which has not finished ({checkpoints})")
    tag = lever_tag(config, checkpoints)
    layout = ActionLayout.from_config(base["layout"])
    metrics_path, sums_path = evaluator_lib.heldout_paths(checkpoints, base["steps"], tag)
    if tag:
        _logged([sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={checkpoints}",
                 f"--step={base['steps']}", *lever_args(config)], folder,
                f"the held-out evaluation of {config} seed {seed}")
        metrics = {k: v for k, v in json.loads(metrics_path.read_text()).items()
                   if k not in ("step", "params", *SAMPLED_LEVERS)}
    else:  # execution levers alone sample the trained config's chunks: its held-out metrics
        metrics = {k: v for k, v in base["metrics"].items() if not k.startswith(CLOSED_LOOP)}
    result = {"config": config, "seed": seed, "steps": base["steps"], "layout": base["layout"],
              "trained": trained,
              "execution": run_execution(saved_config(checkpoints), config).summary(),
              "metrics": metrics,
              EPISODE_REPLICATES: episode_replicates(chunk_sums_lib.load_chunk_sums(sums_path),
                                                     layout)}
    json_files.write_json_atomic(folder / RESULT_FILE, result)
    return result


def add_closed_loop(result: dict[str, Any], workdir: Path, episodes: int) -> dict[str, Any]:
    """The result with the closed-loop metrics and per-episode outcomes of `episodes` episodes
    (measured now when it has none of that many; `result.json` rewritten)."""
    if episodes <= 0 or run_has_closed_loop(result, episodes):
        return result
    metrics, outcomes = closed_loop_metrics(workdir, result["config"], result["seed"],
                                            result["steps"], episodes)
    result = {**result, CLOSED_LOOP_EPISODES: outcomes, "metrics": {
        **{k: v for k, v in result["metrics"].items() if not k.startswith(CLOSED_LOOP)},
        **metrics}}
    json_files.write_json_atomic(run_folder(workdir, result["config"], result["seed"])
                                 / RESULT_FILE, result)
    return result


def run_has_closed_loop(result: Mapping[str, Any], episodes: int) -> bool:
    """Whether a run's result holds the closed-loop metrics and outcomes of `episodes` episodes,
    at every tolerance of the success curve (one measured before those were kept is measured
    again)."""
    return (result["metrics"].get(CLOSED_LOOP + "episodes") == episodes
            and all(has_outcomes(result, curve_prefix(f) + "success/task")
                    for f in LOOSER_TOLERANCES)
            and has_outcomes(result, "success/task"))


# What every result.json holds (`run_one`), with its type.
RESULT_FIELDS = {"config": str, "seed": int, "steps": int, "layout": dict, "metrics": dict}


def load_result(folder: Path) -> dict[str, Any] | None:
    """A finished run's `result.json`, None where there is none.

    Raises:
      ValueError naming the file, what it lacks and the fix, for one that is not JSON or not a
      result's shape (a truncated or hand-edited file).
    """
    path = folder / RESULT_FILE
    if not path.exists():
        return None
    fix = "delete it and rerun the study to evaluate that run again"
    try:
        result = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not JSON ({e}): {fix}") from None
    if not isinstance(result, dict):
        raise ValueError(f"{path} holds a {type(result).__name__}, not a run's result (an "
                         f"object with {sorted(RESULT_FIELDS)}): {fix}")
    wrong = [k for k, kind in RESULT_FIELDS.items() if not isinstance(result.get(k), kind)]
    if wrong:
        raise ValueError(f"{path} lacks a run's {wrong} (or holds them of the wrong type): {fix}")
    return result


def reported_runs(workdir: Path) -> dict[tuple[str, int], dict[str, Any]]:
    """`{(config, seed): result}` of the runs in `workdir`'s `study.json` (none without one)."""
    path = workdir / "study.json"
    if not path.is_file():
        return {}
    try:
        runs = json.loads(path.read_text())["runs"]
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise ValueError(f"{path} is not a study's report ({e!r}); move it away to report the "
                         "run folders alone") from None
    return {(r["config"], int(r["seed"])): r for r in runs}


def run_study(configs: Sequence[str], seeds: Sequence[int], steps: int, workdir: Path,
              overrides: Sequence[str] = (), parallel: int = 1, closed_loop_episodes: int = 0,
              train: bool = True, evaluations: int = 1) -> list[dict[str, Any]]:
    """Every (config, seed) run, the finished ones read back (and evaluated in closed loop when
    they were not), the others trained; with `train=False`, only the finished ones (a partial
    study's tables, labelled by their seed counts), read from `workdir`'s `study.json` where a
    run has no folder (a study kept as its report alone, `results/<study>/`). Lever variants
    (`trained_config`) are measured on the checkpoints of their trained config, which the study
    must hold, each once its seed's trained run has finished."""
    missing = sorted({trained_config(c) for c in configs} - set(configs))
    if train and missing:
        raise ValueError(f"--configs {[c for c in configs if trained_config(c) in missing]} "
                         f"are measured on the checkpoints of {missing}: add them to --configs")
    results, todo, unmeasured = {}, [], []
    reported = {} if train else reported_runs(workdir)
    for seed in seeds:  # seed-major: an interrupted study has every config's first seeds
        for config in configs:
            folder = run_folder(workdir, config, seed)
            result, trained = load_result(folder), run_steps(config, steps)
            if result is None:
                result = reported.get((config, seed))
            if result is not None and result["steps"] == trained:
                result = add_episode_replicates(result, folder, evaluate_missing=train)
                results[config, seed] = result
                if train and closed_loop_episodes > 0 and not run_has_closed_loop(
                        result, closed_loop_episodes):
                    unmeasured.append((config, seed))
            elif result is not None:
                raise ValueError(f"{folder} finished {result['steps']} steps, not "
                                 f"{trained}: use another --workdir")
            else:
                todo.append((config, seed))
    if not train:
        if not results:
            raise ValueError(f"{workdir} has no finished run of {list(configs)}")
        print(f"study: reporting the {len(results)} finished runs of {len(results) + len(todo)}",
              flush=True)
        return [results[c, s] for c in configs for s in seeds if (c, s) in results]
    if todo or unmeasured:
        variants = sum(trained_config(c) != c for c, _ in todo)
        print(f"study: {len(results)} of {len(results) + len(todo)} runs finished; training "
              f"{len(todo) - variants}, lever variants measured on their checkpoints {variants}, "
              f"closed loop for {len(unmeasured)} finished ({parallel} at a time), logs in "
              f"{workdir}/<config>/seed_<s>/train.log", flush=True)
    jobs = {**{(c, s): functools.partial(add_closed_loop, results[c, s], workdir,
                                         closed_loop_episodes) for c, s in unmeasured},
            **{(c, s): functools.partial(run_one, c, s, steps, workdir, overrides,
                                         closed_loop_episodes, evaluations) for c, s in todo}}
    # A lever variant is measured on its trained run's checkpoints: it is queued once that run
    # has finished, behind the trainings, so it takes a slot the last trainings leave free.
    waiting = [key for key in jobs if trained_config(key[0]) != key[0]]
    with (concurrent.futures.ThreadPoolExecutor(max_workers=parallel) as pool,
          tqdm(total=len(jobs), desc="study runs", unit="run") as bar):
        try:
            futures = {pool.submit(jobs[key]): key for key in jobs if key not in waiting}
            while futures or waiting:
                ready = [key for key in waiting if (trained_config(key[0]), key[1]) in results]
                futures.update({pool.submit(jobs[key]): key for key in ready})
                waiting = [key for key in waiting if key not in ready]
                done, _ = concurrent.futures.wait(futures,
                                                  return_when=concurrent.futures.FIRST_COMPLETED)
                for future in done:
                    results[futures.pop(future)] = future.result()
                    bar.update()
        except StudyInterrupted:
            pool.shutdown(wait=True, cancel_futures=True)
            finished = sum(load_result(run_folder(workdir, c, s)) is not None
                           for c in configs for s in seeds)
            raise StudyInterrupted(f"{finished} of {len(configs) * len(seeds)} runs finished"
                                   ) from None
    return [results[c, s] for c in configs for s in seeds]
