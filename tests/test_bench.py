"""The data benchmarks run end to end at a small size and print their numbers (the real sizes
are benchmark commands: RESULTS.md, "Benchmarks")."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _bench(tmp_path, *args: str) -> str:
    env = {**os.environ, "PI0_ARMFIX_CACHE": str(tmp_path / "cache"), "JAX_PLATFORMS": "cpu"}
    result = subprocess.run([sys.executable, "-m", "pi0_armfix.bench", *args], cwd=REPO,
                            env=env, capture_output=True, text=True, timeout=1200)
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout


@pytest.mark.slow  # a whole benchmark
def test_memory_benchmark_reports_each_process_and_the_growth(tmp_path):
    out = _bench(tmp_path, "data", "--part=memory", "--memory_frames=100000,300000",
                 "--memory_workers=1", "--steps=2", "--batch_size=8", "--horizon=10")
    assert out.count("training process: peak") == 2 and out.count("Grain worker: peak") == 2
    assert "growth of the peak RSS from 0 M to 0 M frames" in out
    assert not list((tmp_path / "cache" / "frames").glob("[0-9a-f]*"))  # stores deleted


@pytest.mark.slow  # a whole benchmark run
def test_video_benchmark_reads_the_original_reencodes_and_trains(tmp_path):
    # (PyAV 18.1's libx265 corrupts its heap encoding 48-px frames: sizes it handles.)
    out = _bench(tmp_path, "video", "--episodes=2", "--episode_frames=20", "--head=128",
                 "--wrist=96", "--size=32", "--samples=3", "--batch_size=2", "--steps=2",
                 "--num_workers=0", "--stream_workers=0", "--stream_episodes=2",
                 "--diversity_samples=2000,4000")
    assert "original, random reads:" in out and "re-encode to 32²" in out
    assert "stream from the original, 0 workers:" in out and "resume to the first batch" in out
    assert "diversity, stream" in out and "diversity, random access" in out
    assert "distinct in 4,000 samples" in out
    assert "training iterator on the re-encoded copy, 0 workers" in out
    assert "(32, 32, 3)" in out
    assert "one keyframe per episode" in out and "streamed (data.video_access = 'auto')" in out


@pytest.mark.slow  # a whole benchmark run
def test_video_benchmark_measures_both_access_modes_on_a_short_gop_original(tmp_path):
    out = _bench(tmp_path, "video", "--episodes=2", "--episode_frames=20", "--head=128",
                 "--wrist=96", "--size=32", "--samples=3", "--batch_size=2", "--steps=2",
                 "--stream_workers=0", "--stream_episodes=2", "--original_gop=4",
                 "--stream_stride=3", "--parts=random,stream")
    assert "a keyframe every 4 frames" in out
    assert "frames read on request (data.video_access = 'auto')" in out  # the probe's choice
    assert "at most 4 frames decoded each" in out and "B1K's mean episode" not in out
    assert "random access on the original, 0 workers:" in out
    assert "stream from the original, 0 workers:" in out and "a sample every 3 frames" in out
    assert "diversity" not in out and "re-encode" not in out


@pytest.mark.slow  # a whole benchmark part
def test_video_benchmark_measures_the_frame_cache_against_decoding_on_request(tmp_path):
    out = _bench(tmp_path, "video", "--episodes=2", "--episode_frames=12", "--head=96",
                 "--wrist=64", "--size=32", "--samples=3", "--batch_size=2", "--steps=2",
                 "--num_workers=0", "--original_gop=2", "--parts=cache")
    assert "frame cache: 24 frames x 3 cameras decoded once at 32²" in out
    assert "ms against" in out and "decoded on request (warm decoders)" in out
    assert "training iterator on the original, 0 workers, decoded on request:" in out
    assert "training iterator on the original, 0 workers, from the frame cache:" in out


@pytest.mark.slow  # the slow lane: fault injection
def test_fault_injection_benchmark_kills_restarts_and_finds_every_resume_bitwise(tmp_path):
    out = _bench(tmp_path, "faults", "--kills=2", "--steps=6", "--seed=1")
    assert out.count("  fault ") == 2
    assert "every restart resumed bitwise" in out
    assert "  faults                  2" in out


@pytest.mark.slow  # the slow lane: every part of the model benchmark
def test_model_benchmark_runs_every_part_and_k_flow_samples_cost_less_per_sample(tmp_path):
    out = _bench(tmp_path, "model", "--latency_preset=tiny", "--repeats=1", "--num_steps=2",
                 "--memory_preset=tiny", "--memory_batch=8", "--flow_time_preset=tiny",
                 "--flow_time_batch=2", "--flow_samples=1,4", "--rounds=1", "--steps=1",
                 "--flow_memory_k=2")
    assert "cached prefix KV:" in out and "train step memory per device, preset=tiny" in out
    assert "train step per flow-matching sample, preset=tiny" in out
    assert "train step memory per device at K=2" in out
    flops = {line.split()[0]: float(line.split()[-2].rstrip("x"))
             for line in out.splitlines() if "GFLOP per sample" in line}
    assert flops["K=1"] == 1.0 and flops["K=4"] < 0.6  # one prefix pass for four samples


@pytest.mark.slow  # a whole benchmark
def test_sim_benchmark_prints_the_expert_bound_and_the_step_rate(tmp_path):
    out = _bench(tmp_path, "sim", "--episodes=3", "--policies=expert")
    assert "== expert: 3 episodes" in out and "env steps/s" in out
    assert "task               1.000" in out


@pytest.mark.slow  # the slow lane: four short demo trainings
def test_train_benchmark_prints_throughput_against_the_bounds_and_the_batch_sweep(tmp_path):
    from train_fixtures import write_tiny_demo

    data = write_tiny_demo(tmp_path / "demo")
    out = _bench(tmp_path, "train", "--rounds=1", "--steps=1", "--data_steps=50",
                 "--batch_sizes=16", "--set=model.preset=tiny", f"--set=data.root={data}",
                 "--set=eval.episodes=2", "--set=train.batch_size=8")
    assert "tiny train step, batch 8" in out and "tiny preset, batch 8" in out
    assert "ratio" in out
    for k in (4, 1):
        line = next(line for line in out.splitlines() if line.startswith(f"  K = {k}:"))
        assert "samples/s" in line and "of the compute bound" in line and "FLOP/byte" in line
    assert "  K = 4, batch 16:" in out


def test_the_train_benchmark_refuses_a_change_to_a_key_no_config_holds_before_any_work(capsys):
    from pi0_armfix.bench import train as train_bench

    with pytest.raises(SystemExit):
        train_bench.main(["bench train", "--set=model.nope=1"])
    assert "--set=model.nope=1: name a config key" in capsys.readouterr().err


@pytest.mark.slow  # a whole benchmark run: the slow lane
def test_the_step_benchmark_times_the_projects_train_step_and_counts_its_flops():
    from pi0_armfix.bench import step as step_bench

    config = step_bench.load_config("arm_focused:b1k", preset="tiny", batch=4, flow_samples=2)
    result = step_bench.measure(config, remat="on", steps=2, peak=1.0, matmul_size=128)
    assert result["batch"] == 4 and result["flow_samples"] == 2 and result["remat"]
    assert result["step_s"] > 0 and result["samples_per_s"] == 4 / result["step_s"]
    assert result["loss"] > 0 and result["compiled_total_gib"] > result["compiled_state_gib"] > 0
    # rematerialization recomputes the forward pass: more hardware than model FLOPs
    assert result["hardware_tflop_per_step"] > result["model_tflop_per_step"] > 0
    assert result["mfu"] == result["model_tflops_per_s"] / 1.0
    assert "MFU" in step_bench.format_result(result)


@pytest.mark.slow
def test_the_step_benchmark_asks_the_compiler_for_memory_without_running_a_step():
    from pi0_armfix.bench import step as step_bench

    config = step_bench.load_config("arm_focused_lora:b1k", preset="tiny", batch=4)
    result = step_bench.measure(config, run=False)
    assert result["lora"] == ("paligemma", "action_expert") and "step_s" not in result
    lines = step_bench.format_result(result).splitlines()
    assert "with LoRA on paligemma, action_expert" in lines[1] and "median" not in lines[1]
    assert lines[2].startswith("memory       compiled") and "peak" not in lines[2]


def test_the_step_benchmark_knows_the_peak_of_the_gpus_users_have():
    from pi0_armfix.bench import step as step_bench

    assert step_bench.peak_tflops("NVIDIA H200") == 989.0
    assert step_bench.peak_tflops("NVIDIA A100-SXM4-80GB") == 312.0
    assert step_bench.peak_tflops("cpu") is None and step_bench.peak_tflops("cpu", 2.0) == 2.0


def test_the_bench_dispatcher_prints_its_usage_on_help_and_exits_0(capsys):
    from pi0_armfix.bench import __main__ as bench_main
    bench_main.main(["pi0-armfix-bench", "--help"])
    assert "NAME --help" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="'nope' is no benchmark"):
        bench_main.main(["pi0-armfix-bench", "nope"])


@pytest.mark.slow  # a whole benchmark
def test_step_flops_count_the_whole_batch_with_or_without_microbatches():
    from pi0_armfix.bench import step as bench_step
    flops = [bench_step.Step(bench_step.load_config(
        "uniform", preset="tiny", batch=4, changes=(f"train.microbatches={n}",))).flops(remat=False)
        for n in (1, 2)]
    assert flops[1] == pytest.approx(flops[0], rel=1e-3)


@pytest.mark.slow  # eleven short processes: the slow lane
def test_the_walltime_benchmark_times_each_part_of_a_run_with_and_without_the_cache(tmp_path):
    from train_fixtures import write_tiny_demo

    data = write_tiny_demo(tmp_path / "demo")
    output = tmp_path / "walltime.json"
    out = _bench(tmp_path, "walltime", "--config=configs/uniform.py", "--steps=2",
                 "--evaluations=1", "--episodes=1", "--repeats=1", f"--output={output}",
                 "--set=model.preset=tiny", f"--set=data.root={data}", "--set=eval.episodes=2",
                 "--set=eval.max_chunks=8", "--set=train.batch_size=8")
    for row in ("| train: whole process |", "| train: first step (compiled) |",
                "| train: evaluation at step 2 |", "| closed loop: whole process |",
                "| closed loop: 1 episodes (the first replan compiles) |",
                "| server: start to /healthz (load, warm-up) |"):
        assert row in out, row
    assert ("| before: no compilation cache, median [min, max] s | first run: the cache filled, "
            in out)
    measured = json.loads(output.read_text())
    assert measured["demo_generation"] is None  # the run reads its own data
    passes = measured["passes"]
    assert [len(passes[mode]) for mode in ("before", "first", "after")] == [1, 1, 1]
    assert passes["before"][0].keys() == passes["first"][0].keys() == passes["after"][0].keys()
