"""A study's report: `study.md` (every table beside the do-nothing rows) and `study.png`, from
`aggregate.aggregate` (the learning curves: `study/curves.py`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pi0_armfix.evaluation import intervals
from pi0_armfix.sim.outcomes import FAILURE_REASONS  # noqa: E402
from pi0_armfix.study.aggregate import (  # noqa: E402
    CLOSED_LOOP, CLOSED_LOOP_KINDS, CLOSED_LOOP_TOLERANCES, COMPARED, COMPARED_HEADINGS,
    CURVE_COMPARED, PHASE_KINDS, SWITCH_COUNTS, SWITCH_METRICS, as_number, curve_prefix)
from pi0_armfix.evaluation.chunk_sums import MEAN_OF_DRAWS  # noqa: E402

GROUP_TABLES = (  # study.md's per-group tables: (metric, heading, digits)
    ("skill", "Skill over persistence of the single draw, what a robot executes (1 - err / "
     "persistence err; > 0: better than holding the previous action, 1: perfect)", 3),
    (f"{MEAN_OF_DRAWS}/skill", "Skill over persistence of the mean of the N draws (the "
     "sampler's own spread averaged away; a do-nothing predictor is its own mean)", 3),
    ("energy_skill", "Energy-score skill over persistence (1 - ES / persistence's; the N draws "
     "scored as a distribution by a proper scoring rule: neither a spread-free bias nor noise "
     "is rewarded)", 3),
    ("motion_gain", "Motion gain (1 = moves like the data, 0 = still, or moving in unrelated "
     "directions)", 3),
    ("motion_ratio", "Motion ratio (magnitude only: 1 = moves as much as the data, in any "
     "direction)", 3),
    ("err", "Error (MSE of the sampled chunk)", 4),
)




def _cell(summary: Mapping[str, Any], key: str, digits: int = 3) -> str:
    mean, std = summary["mean"].get(key), summary["std"].get(key)
    if mean is None:
        return "n/a"
    return f"{mean:.{digits}f} ± {std:.{digits}f}"


def _value(metrics: Mapping[str, Any] | None, key: str, digits: int = 3) -> str:
    value = None if metrics is None else metrics.get(key)
    return "n/a" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def _interval(d: Sequence[float]) -> str:
    """`+0.123 [+0.010, +0.200]`."""
    if not np.isfinite(d[0]):
        return "n/a"
    if not np.isfinite(d[1]):
        return f"{d[0]:+.3f} [n/a: 1 seed]"
    return f"{d[0]:+.3f} [{d[1]:+.3f}, {d[2]:+.3f}]"


def _reference_rows(study: Mapping[str, Any], key_of_group, digits: int = 3) -> list[str]:
    """The do-nothing rows (and the ceiling, where known) of a per-group table, in italics."""
    rows = []
    named = [(f"*{name.replace('_', ' ')} (do nothing)*", m)
             for name, m in study["do_nothing"].items()]
    if study.get("ceiling"):
        named.append(("*ceiling: the expert re-run (perfect sampler)*", study["ceiling"]))
    for label, m in named:
        cells = [_value(m, key_of_group(g), digits) for g in study["groups"]]
        rows.append(f"| {label} | " + " | ".join(cells) + " |")
    return rows


def execution_lines(configs: Mapping[str, Any]) -> list[str]:
    """How each config's policy was executed (`eval.execution` with its levers,
    `policies/sampling.py`): one line where every config shares it, else one per config."""
    executions = {name: c.get("execution", "not recorded") for name, c in configs.items()}
    if set(executions.values()) == {"not recorded"}:
        return ["Execution: not recorded by these runs (kept before the study recorded it); a "
                "lever variant executes its trained config's way with the levers its name "
                "sets."]
    if len(set(executions.values())) == 1:
        return [f"Execution, every config alike: {next(iter(executions.values()))}."]
    return ["Execution, by config:", "", *(f"- `{name}`: {text}"
                                          for name, text in executions.items())]


def markdown(study: Mapping[str, Any], *, steps: int, command: str) -> str:
    """`study.md`: the tables of `aggregate`, every one with the do-nothing rows."""
    groups, configs = study["groups"], study["configs"]
    seeds = study["min_seeds"]
    targets = study["targets"]
    header = "| config | " + " | ".join(groups) + " |"
    rule = "|---" * (len(groups) + 1) + "|"
    counts = {name: len(c["seeds"]) for name, c in configs.items()}
    most = max(counts.values())
    per_config = f"{most}" if seeds == most else f"{seeds}-{most}"
    lines = [f"# Study: {len(configs)} configs x {per_config} seeds, {steps} steps", "",
             f"`{command}`", "", *execution_lines(configs), ""]
    if study["anecdotal"]:
        few = [f"{name} ({n})" for name, n in counts.items() if n < intervals.MIN_SEEDS]
        lines += [f"**Fewer than {intervals.MIN_SEEDS} seeds for {', '.join(few)}: their "
                  "intervals below are anecdotes, not results.**", ""]
    lines += ["Held-out chunks sampled by the policy, mean ± std over seeds, every seed on the "
              "same chunks (evaluation units: absolute actions over each dim's training std). "
              "Rows in italics are the do-nothing predictors on the same chunks: *persistence* "
              "holds the previous action, *state copy* repeats the current state where it maps "
              "to the actions (see docs/evaluation.md).", ""]
    for metric, title, digits in GROUP_TABLES:
        lines += [f"## {title}", "", header, rule]
        lines += [f"| {name} | " + " | ".join(_cell(c, f"{metric}/{g}", digits) for g in groups)
                  + " |" for name, c in configs.items()]
        reference = metric.removeprefix(f"{MEAN_OF_DRAWS}/")
        lines += _reference_rows(study, lambda g, m=reference: f"{m}/{g}", digits) + [""]
    lines = lines[:-1]
    lines += ["", "## Gripper switches (each event of the held-out timeline once, matched within "
              "the tolerance)", "",
              "| config | precision | recall | F1 | TP / FP / FN (mean over seeds) |",
              "|---|---|---|---|---|"]
    for name, c in configs.items():
        counts = " / ".join(_value(c["mean"], f"gripper_switch/{k}", 1) for k in SWITCH_COUNTS)
        lines.append(f"| {name} | " + " | ".join(_cell(c, f"gripper_switch/{k}")
                                                 for k in SWITCH_METRICS) + f" | {counts} |")
    for label, m in [(f"*{n.replace('_', ' ')} (do nothing)*", m)
                     for n, m in study["do_nothing"].items()]:
        counts = " / ".join(_value(m, f"gripper_switch/{k}", 0) for k in SWITCH_COUNTS)
        lines.append(f"| {label} | " + " | ".join(_value(m, f"gripper_switch/{k}")
                                                 for k in SWITCH_METRICS) + f" | {counts} |")
    resampled = study.get("episode_resampling")
    if not resampled:
        sampling = ("the seeds' spread only: some runs lack their per-chunk sums, so the "
                    "interval speaks for these held-out episodes alone")
    elif resampled["episodes"] < 2:  # one episode's resamples are itself: no spread to see
        sampling = ("the seeds' spread only: one held-out episode gives no sampling error to "
                    "estimate, so the interval speaks for that episode alone")
    else:
        sampling = (f"the seeds' spread and the held-out episodes' sampling error "
                    f"({resampled['episodes']} episodes, {resampled['replicates']} bootstrap "
                    "resamples shared by every run)")
    lines += ["", f"## Against `{study['baseline']}` (difference of means over seeds, Welch t "
              "interval)", "",
              f"Levels: the primary comparison, `{study['primary']}`, at "
              f"{configs[study['primary']]['confidence']:.1%}; the other trained configs with "
              ">= 2 seeds (secondary) and the other lever variants are two families, each "
              "Bonferroni-corrected over its members, so that in each column a family's "
              "intervals hold together at 95 %; each row's level is in its comparison column. "
              f"The intervals hold {sampling}. An interval that excludes 0 is a difference "
              "these seeds and episodes can tell.", "",
              "| config | comparison | " + " | ".join(COMPARED_HEADINGS) + " |",
              "|---" * (len(COMPARED) + 2) + "|"]
    for name, c in configs.items():
        if c["comparison"] == "baseline":
            lines.append(f"| {name} | the baseline | " + " | ".join("—" for _ in COMPARED) + " |")
            continue
        vs = c["vs_baseline"]
        level = f"{c['comparison']} ({c['confidence']:.1%})"
        lines.append(f"| {name} | {level} | " + " | ".join(_interval(vs[k]) for k in COMPARED)
                     + " |")
    lines += group_skill_table(study, sampling)
    lines += group_comparison_table(study, sampling)
    lines += ["", "## Targets", "",
              f"Arms' skill over persistence > 0 with its 95 % interval above 0; each arm's "
              f"motion gain >= {targets['arm_gain']} (or >= {targets['ceiling_share']:.0%} of the "
              f"ceiling where that is below {targets['ceiling_below']}); base skill at most "
              f"{targets['base_skill_drop']:.0%} below `{study['baseline']}`'s; gripper switch "
              f"F1 >= {targets['switch_f1']}.", "",
              "| config | arms' skill [95 %] | arm skill | arm gain | base skill | switch F1 |",
              "|---|---|---|---|---|---|"]
    for name, c in configs.items():
        met = c["targets"]
        lines.append(f"| {name} | {_interval(c['arm_skill_interval'])} | "
                     + " | ".join(_verdict(met[k]) for k in
                                  ("arm_skill", "arm_gain", "base_skill", "switch_f1")) + " |")
    if any_config_has_closed_loop(configs):
        lines += closed_loop_table(study)
    return "\n".join(lines + lever_table(configs)) + "\n"


def _verdict(met: bool | None) -> str:
    return "n/a" if met is None else "met" if met else "missed"


def group_skill_table(study: Mapping[str, Any], sampling: str) -> list[str]:
    """study.md's per-group skill over persistence of each config with its 95 % interval (the
    question whether a group beats holding the previous action, not whether it beats the
    baseline): single draw, then the mean of the draws."""
    configs = {n: c for n, c in study["configs"].items() if "group_intervals" in c}
    return _group_table(study, configs, "group_intervals", sampling, [
        "## Each group against holding the previous action (skill over persistence, 95 % "
        "interval per cell, uncorrected)", "Each group's mean skill over seeds; each cell's "
        "95 % interval stands alone (no correction over groups or configs) and holds "
        "{episodes}. Above 0: the group beats holding the previous action at these seeds and "
        "episodes. Single draw, then the mean of the draws."])


def group_comparison_table(study: Mapping[str, Any], sampling: str) -> list[str]:
    """study.md's per-group differences to the baseline: each group's skill over persistence,
    the single draw's and the mean of the draws', with the comparison's interval."""
    configs = {n: c for n, c in study["configs"].items() if "vs_baseline_groups" in c
               and c["comparison"] != "baseline"}
    return _group_table(study, configs, "vs_baseline_groups", sampling, [
        f"## Against `{study['baseline']}`, per group (skill over persistence)",
        "Each group's difference of means over seeds, at each comparison's level (above); the "
        "intervals hold {episodes}. Single draw, then the mean of the draws."])


def _group_table(study: Mapping[str, Any], configs: Mapping[str, Any], key: str, sampling: str,
                 heading: Sequence[str]) -> list[str]:
    """A per-group table of `configs`' intervals `c[key]` (single draw and mean of the draws),
    under `heading` (the title and the text, whose `{episodes}` says what the intervals hold)."""
    if not configs:
        return []
    groups = study["groups"]
    episodes = (sampling if all(c["groups_resampled"] for c in configs.values())
                else "the seeds' spread alone (some runs kept no per-group resamples)")
    title, text = heading
    lines = ["", title, "", text.format(episodes=episodes), "",
             "| config | draw | " + " | ".join(groups) + " |", "|---" * (len(groups) + 2) + "|"]
    for name, c in configs.items():
        for label, prefix in (("single", ""), ("mean of draws", f"{MEAN_OF_DRAWS}/")):
            lines.append(f"| {name} | {label} | " + " | ".join(
                _interval(c[key][f"{prefix}skill/{g}"]) for g in groups) + " |")
    return lines


def lever_table(configs: Mapping[str, Any]) -> list[str]:
    """study.md's lever variants against their trained configs (`aggregate.lever_comparisons`:
    paired seed for seed); nothing when the study has none."""
    levers = {name: c for name, c in configs.items() if "vs_trained" in c}
    if not levers:
        return []
    loop = [*(f"{CLOSED_LOOP}phase_success/{k}" for k in PHASE_KINDS),
            f"{CLOSED_LOOP}success/task"]
    headings = [*COMPARED_HEADINGS, "navigation phases", "manipulation phases", "task"]
    lines = ["", "## Inference levers against the trained config they sample (paired)", "",
             "Each lever variant samples its trained config's checkpoints, seed for seed: the "
             "difference of the two, mean over seeds with the t interval of the per-seed "
             "differences at the variant's level in the table above (the primary's 95 %; the "
             "others Bonferroni-corrected over the lever variants, per column), widened by the "
             "held-out (world) episodes' sampling error of the difference. The executed chunk "
             "is the variant's (the single draw of its sampler); "
             "the closed-loop columns are phase and task success in the demo world.", "",
             "| lever variant | against | " + " | ".join(headings) + " |",
             "|---" * (len(headings) + 2) + "|"]
    for name, c in levers.items():
        vs = c["vs_trained"]
        lines.append(f"| {name} | {c['trained']} | " + " | ".join(
            _interval(vs[k]) if k in vs else "n/a" for k in [*COMPARED, *loop]) + " |")
    return lines + tolerance_table(levers, "vs_trained")


def tolerance_table(configs: Mapping[str, Any], versus: str) -> list[str]:
    """The closed-loop differences (`versus`: "vs_baseline" or "vs_trained") at the world's
    tolerance and at each looser factor of the success curve, with their intervals; nothing when
    no config has a difference at a looser factor."""
    if not any(CLOSED_LOOP + k in c[versus] for c in configs.values() for k in CURVE_COMPARED):
        return []
    rates = [f"phase_success/{k}" for k in PHASE_KINDS] + ["success/task"]
    columns = [(f, ("" if f == 1 else curve_prefix(f)) + r)
               for f in CLOSED_LOOP_TOLERANCES for r in rates]
    against = ("the trained config it samples (paired seed for seed)" if versus == "vs_trained"
               else "the baseline (Welch, over seeds)")
    lines = ["", f"The same difference to {against} at the world's tolerances (1x) and with "
             "every tolerance times 2 and 4 (the same episodes; the intervals widened by their "
             "sampling error at each factor): navigation phases, manipulation phases, task.", "",
             "| config | " + " | ".join(f"{k.split('/')[-1]} at {f:g}x" for f, k in columns)
             + " |",
             "|---" * (len(columns) + 1) + "|"]
    for name, c in configs.items():
        vs = c[versus]
        lines.append(f"| {name} | " + " | ".join(
            _interval(vs[CLOSED_LOOP + k]) if CLOSED_LOOP + k in vs else "n/a"
            for _, k in columns) + " |")
    return lines


def any_config_has_closed_loop(configs: Mapping[str, Any]) -> bool:
    """Whether any config of an aggregate has closed-loop metrics."""
    return any(f"{CLOSED_LOOP}success/task" in c["mean"] for c in configs.values())


def closed_loop_table(study: Mapping[str, Any]) -> list[str]:
    """study.md's closed-loop section: success per kind, mean ± std over seeds, vs the baseline;
    the success curve; the closed-loop targets."""
    configs = study["configs"]
    episodes = {c["mean"].get(CLOSED_LOOP + "episodes") for c in configs.values()}
    compared = [f"phase_success/{k}" for k in PHASE_KINDS] + ["success/task"]
    lines = ["", "## Closed loop in the demo world (`pi0_armfix.sim`)", "",
             f"{', '.join(str(int(e)) for e in sorted(e for e in episodes if e))} episodes per "
             "seed (world seed 1000, never trained on), the world's tolerances (what each means "
             "physically: docs/evaluation.md). Phases: the share of a kind's phases that "
             "succeeded; episodes: the share of episodes whose every phase of that kind "
             "succeeded; mean ± std over seeds. Then the difference to the baseline "
             "[Welch t interval over seeds, widened by the world episodes' sampling error]. "
             "Progress: how far a phase got, 1 - closest approach / start distance, mean over "
             "phases.", "",
             "| config | navigation phases | manipulation phases | navigation episodes | "
             "manipulation episodes | task | navigation progress | manipulation progress | "
             "vs baseline: navigation phases | manipulation phases | task |", "|---" * 11 + "|"]
    for name, c in configs.items():
        vs = c["vs_baseline"]
        diffs = [_interval(vs[CLOSED_LOOP + k]) if CLOSED_LOOP + k in vs else "n/a"
                 for k in compared]
        lines.append(f"| {name} | " + " | ".join(
            [_cell(c, f"{CLOSED_LOOP}phase_success/{k}") for k in PHASE_KINDS]
            + [_cell(c, f"{CLOSED_LOOP}success/{k}") for k in CLOSED_LOOP_KINDS]
            + [_cell(c, f"{CLOSED_LOOP}progress/{k}") for k in PHASE_KINDS] + diffs) + " |")
    return (lines + tolerance_table(configs, "vs_baseline") + failure_table(configs)
            + success_curve_table(configs) + closed_loop_targets(study))


def success_curve_table(configs: Mapping[str, Any]) -> list[str]:
    """The share of phases that succeeded with the world's tolerances times 1, 2 and 4."""
    factors = [f for f in CLOSED_LOOP_TOLERANCES
               if any(f"{CLOSED_LOOP}curve/{f:g}x/phase_success/manipulation" in c["mean"]
                      for c in configs.values())]
    if not factors:
        return []
    columns = [(k, f) for k in PHASE_KINDS for f in factors]
    lines = ["", "Success curve: the share of phases that succeeded when every tolerance of the "
             "world (radius, heading, stopped, reach) is multiplied by the factor, the same "
             "episodes, mean ± std over seeds.", "",
             "| config | " + " | ".join(f"{k} phases at {f:g}x" for k, f in columns) + " |",
             "|---" * (len(columns) + 1) + "|"]
    for name, c in configs.items():
        lines.append(f"| {name} | " + " | ".join(
            _cell(c, f"{CLOSED_LOOP}curve/{f:g}x/phase_success/{k}") for k, f in columns) + " |")
    return lines


def closed_loop_targets(study: Mapping[str, Any]) -> list[str]:
    """Which config meets the closed-loop targets (`aggregate.Targets`)."""
    targets = study["targets"]
    rows = [(n, c["targets"]) for n, c in study["configs"].items()
            if "closed_loop_manipulation" in c["targets"]]
    if not rows:
        return []
    lines = ["", f"Closed-loop targets: manipulation phases at least "
             f"{targets['manipulation_gain']:.0%} points above `{study['baseline']}`'s with the "
             f"interval above 0; navigation phases at most {targets['navigation_drop']:.0%} "
             f"points below; held-out gripper switch precision >= "
             f"{targets['switch_precision']}.", "",
             "| config | manipulation phases | navigation phases | switch precision |",
             "|---|---|---|---|"]
    for name, met in rows:
        lines.append(f"| {name} | " + " | ".join(
            _verdict(met[k]) for k in
            ("closed_loop_manipulation", "closed_loop_navigation", "switch_precision")) + " |")
    return lines


def failure_table(configs: Mapping[str, Any]) -> list[str]:
    """Why the phases failed: per config, the fraction of its phases that failed for each reason
    (`sim.outcomes.FAILURE_REASONS`, mean over seeds), and the gripper switches per phase."""
    reasons = [(kind, reason) for kind in PHASE_KINDS
               for reason in FAILURE_REASONS[kind]]
    if not any(f"{CLOSED_LOOP}failure/{k}/{r}" in c["mean"] for c in configs.values()
               for k, r in reasons):
        return []
    lines = ["", "Why phases failed: the fraction of a kind's phases that failed for each reason "
             "(the furthest stage the phase reached; see docs/evaluation.md), mean over seeds; "
             "gripper switches: open/close commands per phase.", "",
             "| config | " + " | ".join(f"{k[:3]}: {r}" for k, r in reasons)
             + " | switches per navigation phase | per manipulation phase |",
             "|---" * (len(reasons) + 3) + "|"]
    for name, c in configs.items():
        cells = [c["mean"].get(f"{CLOSED_LOOP}failure/{k}/{r}") for k, r in reasons]
        cells += [c["mean"].get(f"{CLOSED_LOOP}gripper_switches/{k}")
                  for k in PHASE_KINDS]
        lines.append(f"| {name} | " + " | ".join(
            "n/a" if v is None or not math.isfinite(v) else f"{v:.2f}" for v in cells) + " |")
    return lines


CLOSED_LOOP_PANEL = ("phase_success/navigation", "phase_success/manipulation", "success/task")
# Below this skill a linear axis squeezes every value near 0 (where the levers differ) into a
# sliver; the axis turns symmetric-log instead, linear within 1 of 0.
LINEAR_SKILL_FLOOR = -3.0


def fit_skill_axis(ax: Any, top: float) -> None:
    """Sets a skill axis (at most 1, unbounded below) to show every value drawn on it: linear
    where the lowest is above `LINEAR_SKILL_FLOOR`, symmetric-log (linear in [-1, 1]) where not,
    so that a group tens of times worse than doing nothing stays on the figure beside groups near
    0. `top`: the axis' upper end."""
    if ax.get_ylim()[0] < LINEAR_SKILL_FLOOR:
        ax.set_yscale("symlog", linthresh=1.0)
    ax.set_ylim(top=top)


def plot_study(study: Mapping[str, Any], path: Path) -> None:
    """`study.png`: per group, each config's skill over persistence and motion gain (mean, std
    over seeds as error bars), the do-nothing predictors as black markers (and the ceiling, where
    known, as grey ones); closed-loop success beside them when the runs have it."""
    groups, configs = study["groups"], study["configs"]
    width = 0.8 / len(configs)
    closed = any_config_has_closed_loop(configs)
    panels = [("skill", "skill over persistence (> 0: better than doing nothing)"),
              ("motion_gain", "motion gain (1 = moves like the data)")]
    fig, axes = plt.subplots(1, len(panels) + closed, squeeze=False, gridspec_kw={
        "width_ratios": [len(groups)] * len(panels)
        + ([len(CLOSED_LOOP_PANEL)] if closed else [])},
        figsize=(2 * max(7, 1.4 * len(groups) + 0.25 * len(configs)) + (4 if closed else 0), 5))
    x = np.arange(len(groups))
    references = [(name, m, "k", marker) for (name, m), marker
                  in zip(study["do_nothing"].items(), ("_", "x"))]
    if study.get("ceiling"):
        references.append(("ceiling (expert re-run)", study["ceiling"], "gray", "*"))
    for ax, (metric, title) in zip(axes[0], panels):
        for i, (name, c) in enumerate(configs.items()):
            means = [c["mean"].get(f"{metric}/{g}") for g in groups]
            stds = [c["std"].get(f"{metric}/{g}") for g in groups]
            ax.bar(x + (i - (len(configs) - 1) / 2) * width,
                   [np.nan if m is None else m for m in means], width,
                   yerr=[0 if s is None else s for s in stds], capsize=2, label=name)
        for name, m, color, marker in references:
            ax.scatter(x, [as_number(m.get(f"{metric}/{g}")) for g in groups], color=color,
                       marker=marker, s=160 if marker == "_" else 50, zorder=3, label=name)
        ax.axhline(0.0, color="black", lw=0.8)
        if metric == "motion_gain":
            ax.axhline(1.0, color="gray", lw=0.8)
        else:
            fit_skill_axis(ax, top=1.1)
        ax.set_xticks(x, groups, rotation=20)
        ax.set(title=title)
        ax.grid(axis="y", alpha=0.3)
    if closed:
        ax = axes[0, -1]
        x = np.arange(len(CLOSED_LOOP_PANEL))
        for i, (name, c) in enumerate(configs.items()):
            keys = [CLOSED_LOOP + k for k in CLOSED_LOOP_PANEL]
            ax.bar(x + (i - (len(configs) - 1) / 2) * width,
                   [np.nan if c["mean"].get(k) is None else c["mean"][k] for k in keys], width,
                   yerr=[c["std"].get(k) or 0 for k in keys], capsize=2, label=name)
        ax.set_xticks(x, ["navigation\nphases", "manipulation\nphases", "task"])
        ax.set(ylim=(0, 1.05), ylabel="success rate", title="closed loop (demo world)")
        ax.grid(axis="y", alpha=0.3)
    axes[0, -1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    seeds = study["min_seeds"]
    fig.suptitle(f"held-out evaluation, mean ± std over {seeds} seed(s) per config "
                 f"(baseline: {study['baseline']})"
                 + (" - fewer than 5 seeds: an anecdote" if study["anecdotal"] else ""))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
