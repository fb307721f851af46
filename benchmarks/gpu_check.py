"""The CUDA path of apply / predict / adapt / eval, and GPU timings (needs a CUDA device).

Nothing in raytun3r needs a GPU, and CI has none: this script is what a session with a lent GPU
runs once to check that the library's promises hold there too, and to time it. Each check
prints PASS or FAIL with its numbers (a failing check does not stop the others); the timings
follow. ``--out DIR`` also writes ``gpu_check.json``.

Checks (the built-in network v3, 112 px, TF32 off so float32 means float32):

* ``pinhole identity``: a pinhole camera, the zero adapter and every correction give the
  unpatched model's outputs (invariant 1), on the GPU.
* ``gpu equals cpu``: a 185-degree fisheye with a nonzero adapter gives the same depth on the GPU
  as on the CPU (relative difference, float32 on both).
* ``remove is exact``: outputs and state_dict after ``remove()`` equal those before ``apply``.
* ``two models``: two models on the GPU patched with different cameras give each one's outputs.
* ``bf16 autocast``: the patched model runs under ``torch.autocast("cuda", torch.bfloat16)`` and
  stays near its float32 output.
* ``adapt``: a self-supervised, a pinhole-view teacher and a supervised fit on the GPU (the
  backbone's weights stay bit-identical; the tables agree with the same fit on the CPU).
* ``eval``: vanilla, Center-PH, Multi-PH and raytun3r through ``run_method`` on the GPU score like
  on the CPU.
* ``lora``: LoRA injected into a model on the GPU starts as the identity and trains.

Timings (random-weight ``da3-small`` / ``da3-base`` / ``da3-large`` from DA3's own configs, 504 px,
a 195-degree fisheye, a nonzero adapter, every correction on): patched over unpatched forward
(CUDA events, interleaved, median of per-repeat ratios), in float32 and under bf16 autocast; one
adaptation step over a plain forward + backward; a whole default ``adapt()`` of da3-small at
504 px (300 steps), with its preparation (matching on the CPU) timed apart.

    python benchmarks/gpu_check.py [--out DIR] [--skip-timings] [--skip-adapt-run]
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import statistics
import tempfile
import time
import traceback
from pathlib import Path

import torch

RESULTS: dict[str, dict] = {}


def check(name: str):
    """Run the decorated check now; record PASS / FAIL / ERROR with its numbers."""

    def run(function):
        began = time.perf_counter()
        try:
            passed, numbers = function()
            status = "PASS" if passed else "FAIL"
        except Exception as error:  # a check's crash is its result, not the script's
            status, numbers = "ERROR", {"error": f"{type(error).__name__}: {error}"}
            numbers["traceback"] = traceback.format_exc(limit=6)
        numbers["seconds"] = round(time.perf_counter() - began, 2)
        RESULTS[name] = {"status": status, **numbers}
        shown = {k: v for k, v in numbers.items() if k != "traceback"}
        print(f"{status:5s} {name}: {shown}", flush=True)
        if status == "ERROR":
            print(numbers["traceback"], flush=True)
        return function

    return run


def relative(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    return float((a - b).norm() / b.norm().clamp_min(1e-30))


def nonzero_adapter(adapter, seed: int = 0):
    """Tables of the size a fit gives (a few tenths of the PE's scale), deterministic."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        rho = torch.linspace(0, 1, adapter.n_r)[:, None]
        adapter.pe["radial"].copy_(
            rho**2 * torch.randn(1, adapter.embed_dim, generator=generator) * 0.3
        )
        adapter.pe["angular"].copy_(
            torch.randn(adapter.pe["angular"].shape, generator=generator) * 0.05
        )
        if adapter.rope is not None:
            adapter.rope["radial"].copy_(torch.linspace(0, 1, adapter.n_r_rope) ** 2 * 0.5)
    return adapter


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=None)
    parser.add_argument("--skip-timings", action="store_true")
    parser.add_argument("--skip-adapt-run", action="store_true")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument(
        "--device",
        default="cuda",
        help="'cpu' runs every check with a second CPU copy in the GPU's place (a dry run of the "
        "script itself, which proves nothing about CUDA)",
    )
    parser.add_argument("--adapt-steps", type=int, default=300)
    parser.add_argument("--checks", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--sizes", type=int, nargs="+", default=[504], help="timing input sizes")
    parser.add_argument("--networks", nargs="+", default=["da3-small", "da3-base", "da3-large"])
    args = parser.parse_args()
    cuda = torch.device(args.device)
    if cuda.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("gpu_check: needs a CUDA device; torch sees none")
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    name = torch.cuda.get_device_name(0) if cuda.type == "cuda" else "CPU (dry run)"
    print(f"torch {torch.__version__}, {name}, {torch.get_num_threads()} CPU threads", flush=True)

    from raytun3r_plugin.registry import quiet_upstream

    quiet = quiet_upstream()
    quiet.__enter__()
    if args.checks:
        run_checks(cuda)
    if not args.skip_timings:
        timings(args, cuda)
    if not args.skip_adapt_run:
        adapt_run(cuda, args.sizes[0], args.adapt_steps)
    quiet.__exit__(None, None, None)
    failed = [name for name, result in RESULTS.items() if result.get("status") in ("FAIL", "ERROR")]
    print(f"\nchecks: {len(RESULTS) - len(failed)} of {len(RESULTS)} passed; failed: {failed}")
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "gpu_check.json").write_text(json.dumps(RESULTS, indent=1, default=str))


def run_checks(cuda: torch.device) -> None:
    """The checks of the module docstring, on the built-in network at 112 px."""
    import raytun3r_plugin as rt
    from raytun3r_plugin import cameras, synthetic
    from raytun3r_plugin.apps.benchmark import ground_truth_depth
    from raytun3r_plugin.apps.demo import default_network
    from raytun3r_plugin.apps.fits import adapt_config, supervised_config

    size = 112
    cpu_model, _ = default_network()
    gpu_model = copy.deepcopy(cpu_model).to(cuda)
    images = torch.rand(1, 3, 3, size, size, generator=torch.Generator().manual_seed(0))
    fisheye = cameras.fisheye(size, 185.0, "kb4")
    pinhole = cameras.Pinhole(size, size, {"fx": 90.0, "fy": 90.0, "cx": 55.5, "cy": 55.5})

    @check("pinhole identity")
    def _():
        with torch.no_grad():
            plain = rt.predict(gpu_model, images)
            with rt.apply(gpu_model, pinhole, rt.Adapter.for_model(gpu_model, pinhole)):
                patched = rt.predict(gpu_model, images)
        error = float((patched.depth - plain.depth).abs().max() / plain.depth.abs().max())
        return error < 1e-5, {"max_abs_over_scale": error, "device": str(patched.depth.device)}

    adapter = nonzero_adapter(rt.Adapter.for_model(cpu_model, fisheye))

    @check("gpu equals cpu")
    def _():
        with torch.no_grad():
            with rt.apply(cpu_model, fisheye, adapter):
                on_cpu = rt.predict(cpu_model, images)
            with rt.apply(gpu_model, fisheye, adapter):
                on_gpu = rt.predict(gpu_model, images)
        depth = relative(on_gpu.depth, on_cpu.depth)
        pose = relative(on_gpu.cam_from_world, on_cpu.cam_from_world)
        return depth < 1e-4 and pose < 1e-4, {"depth_rel": depth, "pose_rel": pose}

    @check("remove is exact")
    def _():
        before_state = {k: v.clone() for k, v in gpu_model.state_dict().items()}
        with torch.no_grad():
            before = rt.predict(gpu_model, images).depth
            handle = rt.apply(gpu_model, fisheye, adapter)
            rt.predict(gpu_model, images)
            handle.remove()
            after = rt.predict(gpu_model, images).depth
        state = gpu_model.state_dict()
        same_state = state.keys() == before_state.keys() and all(
            torch.equal(state[k], v) for k, v in before_state.items()
        )
        error = float((after - before).abs().max())
        return same_state and error <= 1e-6 * float(before.abs().max()), {
            "output_max_abs": error,
            "state_dict_equal": same_state,
        }

    @check("two models")
    def _():
        other = copy.deepcopy(gpu_model)
        wide = cameras.fisheye(size, 195.0, "ds")
        with torch.no_grad():
            with rt.apply(gpu_model, fisheye, adapter):
                alone_a = rt.predict(gpu_model, images).depth
            with rt.apply(other, wide):
                alone_b = rt.predict(other, images).depth
            with rt.apply(gpu_model, fisheye, adapter), rt.apply(other, wide):
                both_a = rt.predict(gpu_model, images).depth
                both_b = rt.predict(other, images).depth
        error = max(relative(both_a, alone_a), relative(both_b, alone_b))
        return error < 1e-6, {"max_rel": error}

    @check("bf16 autocast")
    def _():
        with torch.no_grad(), rt.apply(gpu_model, fisheye, adapter):
            full = rt.predict(gpu_model, images).depth
            with torch.autocast(cuda.type, dtype=torch.bfloat16):
                half = rt.predict(gpu_model, images).depth
        error = relative(half.float(), full)
        return bool(torch.isfinite(half).all()) and error < 5e-2, {"depth_rel": error}

    sequence = synthetic.render_sequence("indoor", fisheye, n_frames=12, seed=80010)
    frames = sequence.images[:9]

    def fits(config, **kwargs):
        from raytun3r_plugin.adaptation import adapt

        weights = {k: v.clone() for k, v in gpu_model.state_dict().items()}
        on_gpu = adapt(gpu_model, fisheye, frames, config, progress=False, **kwargs)
        untouched = all(torch.equal(v, gpu_model.state_dict()[k]) for k, v in weights.items())
        on_cpu = adapt(cpu_model, fisheye, frames, config, progress=False, **kwargs)
        a = torch.cat([t.detach().flatten() for t in on_gpu.parameters()])
        b = torch.cat([t.detach().flatten() for t in on_cpu.parameters()])
        correlation = float(torch.corrcoef(torch.stack([a, b]))[0, 1])
        return untouched, correlation, on_gpu, on_cpu

    @check("adapt self-supervised")
    def _():
        config = adapt_config(size, 30, n_windows=6, guard_every=10)
        untouched, correlation, on_gpu, on_cpu = fits(config)
        verdict = on_gpu.training_info["verdict"]["status"]
        return untouched and correlation > 0.95, {
            "backbone_bit_identical": untouched,
            "tables_corr_gpu_cpu": correlation,
            "verdict_gpu": verdict,
            "verdict_cpu": on_cpu.training_info["verdict"]["status"],
        }

    @check("adapt teacher")
    def _():
        from raytun3r_plugin.adaptation.config import TEACHER_WEIGHTS
        from raytun3r_plugin.adaptation.losses import LossWeights

        config = adapt_config(
            size,
            30,
            n_windows=6,
            lr=3e-2,
            guard=False,
            weights=LossWeights(**TEACHER_WEIGHTS),
        )
        untouched, correlation, on_gpu, _ = fits(config)
        return untouched and correlation > 0.95, {
            "backbone_bit_identical": untouched,
            "tables_corr_gpu_cpu": correlation,
            "verdict_gpu": on_gpu.training_info["verdict"]["status"],
        }

    @check("adapt supervised")
    def _():
        config = supervised_config(size, 30, n_windows=6)
        untouched, correlation, on_gpu, _ = fits(
            config, depth=ground_truth_depth(sequence, len(frames))
        )
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / "fit.safetensors"
            on_gpu.save(path)
            loaded = rt.Adapter.load(path)
            same = all(
                torch.equal(a.cpu(), b)
                for a, b in zip(on_gpu.parameters(), loaded.parameters(), strict=True)
            )
        return untouched and same and correlation > 0.95, {
            "backbone_bit_identical": untouched,
            "tables_corr_gpu_cpu": correlation,
            "saved_and_loaded_equal": same,
        }

    @check("eval")
    def _():
        from raytun3r_plugin.apps.evaluation import headline, run_method, score

        numbers, worst = {}, 0.0
        for method in ("vanilla", "center-ph", "multi-ph", "raytun3r"):
            extra = {"adapter": adapter} if method == "raytun3r" else {}
            on_gpu = headline(score(sequence, run_method(gpu_model, sequence, method, **extra)))
            on_cpu = headline(score(sequence, run_method(cpu_model, sequence, method, **extra)))
            difference = abs(on_gpu["abs_rel"] - on_cpu["abs_rel"])
            numbers[method] = [round(on_gpu["abs_rel"], 5), round(on_cpu["abs_rel"], 5)]
            worst = max(worst, difference)
        numbers["worst_abs_rel_difference"] = worst
        return worst < 1e-3, numbers

    @check("lora")
    def _():
        from raytun3r_plugin.adaptation import adapt
        from raytun3r_plugin.baselines import inject_lora

        # A copy of the model already on the device: DA3's PositionGetter caches its positions on
        # the device of the first forward, so a model that ran on the CPU cannot be moved after.
        model = copy.deepcopy(gpu_model)
        with torch.no_grad():
            plain = rt.predict(model, images).depth
        with inject_lora(model) as lora:
            with torch.no_grad():
                start = rt.predict(model, images).depth
            adapt(
                model,
                fisheye,
                frames,
                adapt_config(size, 5, n_windows=3, guard=False, min_parallax_px=0.0),
                tune=lora.weights,
                progress=False,
            )
            moved = float(sum(b.detach().abs().sum() for b in lora.weights.lora_B))
        error = relative(start, plain)
        return error < 1e-6 and moved > 0, {"identity_rel": error, "lora_B_abs_sum": moved}


def random_network(name: str, cuda: torch.device) -> torch.nn.Module:
    """A random-weight DA3 network from DA3's own config, random PE table, eval mode, frozen."""
    from raytun3r_plugin.patches.da3_networks import build_network

    torch.manual_seed(0)
    model = build_network(name).eval()
    with torch.no_grad():
        model.backbone.pretrained.pos_embed.normal_(0, 0.02)
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    return model.to(cuda)


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def event_time(function, device: torch.device) -> float:
    """Seconds ``function`` takes: CUDA events on a GPU, the wall clock on the CPU."""
    if device.type != "cuda":
        start = time.perf_counter()
        function()
        return time.perf_counter() - start
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    function()
    end.record()
    torch.cuda.synchronize()
    return start.elapsed_time(end) / 1000.0


def timings(args, cuda: torch.device) -> None:
    import raytun3r_plugin as rt
    from raytun3r_plugin import cameras

    print("\n## forward: patched over unpatched (195-degree fisheye, nonzero adapter)", flush=True)
    print("| network | size | views | precision | unpatched ms | patched ms | median ratio |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for name, size in [(n, s) for n in args.networks for s in args.sizes]:
        camera = cameras.fisheye(size, 195.0, "kb4", k=(0.0, 0.0, 0.0, 0.0))
        try:
            plain = random_network(name, cuda)
        except Exception as error:
            print(f"| {name} | - | - | {type(error).__name__}: {error} | | |", flush=True)
            continue
        patched = copy.deepcopy(plain)
        adapter = nonzero_adapter(rt.Adapter.for_model(patched, camera))
        for views in (2, 8):
            images = torch.rand(
                1, views, 3, size, size, generator=torch.Generator().manual_seed(views)
            ).to(cuda)
            for precision in ("fp32", "bf16"):
                context = (
                    torch.autocast(cuda.type, dtype=torch.bfloat16)
                    if precision == "bf16"
                    else torch.autocast(cuda.type, enabled=False)
                )
                with torch.inference_mode(), context, rt.apply(patched, camera, adapter):
                    for _ in range(3):
                        rt.predict(plain, images), rt.predict(patched, images)
                    synchronize(cuda)
                    a_times, b_times, ratios = [], [], []
                    for repeat in range(args.repeats):
                        order = (plain, patched) if repeat % 2 == 0 else (patched, plain)
                        measured = {
                            id(model): event_time(lambda m=model, x=images: rt.predict(m, x), cuda)
                            for model in order
                        }
                        a, b = measured[id(plain)], measured[id(patched)]
                        a_times.append(a)
                        b_times.append(b)
                        ratios.append(b / a)
                row = {
                    "network": name,
                    "size": size,
                    "views": views,
                    "precision": precision,
                    "unpatched_ms": 1000 * statistics.median(a_times),
                    "patched_ms": 1000 * statistics.median(b_times),
                    "ratio": statistics.median(ratios),
                }
                rows.append(row)
                print(
                    f"| {name} | {size} | {views} | {precision} | {row['unpatched_ms']:.1f} | "
                    f"{row['patched_ms']:.1f} | {row['ratio']:.3f} |",
                    flush=True,
                )
        del plain, patched
        if cuda.type == "cuda":
            torch.cuda.empty_cache()
    RESULTS["timings forward"] = {"rows": rows}


def adapt_run(cuda: torch.device, size: int, steps: int) -> None:
    """One default adapt() of da3-small at 504 px on the GPU (300 steps), and the cost of one
    step over a plain forward + backward."""
    import raytun3r_plugin as rt
    from raytun3r_plugin import cameras, synthetic
    from raytun3r_plugin.adaptation import AdaptConfig, adapt
    from raytun3r_plugin.adaptation.problem import prepare_problem
    from raytun3r_plugin.adaptation.step import adaptation_step

    camera = cameras.fisheye(size, 190.0, "kb4", k=(0.0, 0.0, 0.0, 0.0))
    began = time.perf_counter()
    frames = synthetic.render_sequence(
        "indoor", camera, n_frames=32, seed=0, supersample=1, num_threads=None
    ).images
    render_s = time.perf_counter() - began
    model = random_network("da3-small", cuda)
    with tempfile.TemporaryDirectory() as folder:
        config = AdaptConfig(
            input_size=size, cache_dir=folder, checkpoint_every=0, steps=steps
        ).resolved_for(model)
        began = time.perf_counter()
        problem = prepare_problem(camera, frames, config)
        prepare_s = time.perf_counter() - began
        print(
            f"\n## adaptation, da3-small at {size} px on {cuda.type}: render 32 frames {render_s:.1f} s, "
            f"matching + MAGSAC++ (CPU) {prepare_s:.1f} s, {len(problem.windows)} windows",
            flush=True,
        )
        adapter = rt.Adapter.for_model(model, problem.layout.native_camera)
        optimizer = torch.optim.Adam(list(adapter.parameters()), lr=config.step_size())
        step_times, plain_times = [], []
        with rt.apply(model, problem.layout.native_camera, adapter):
            for step in range(12):
                synchronize(cuda)
                start = time.perf_counter()
                adaptation_step(model, adapter, optimizer, problem, config, step, index=0)
                synchronize(cuda)
                step_times.append(time.perf_counter() - start)
                start = time.perf_counter()
                prediction = rt.predict(model, problem.batch(0)[None])
                optimizer.zero_grad(set_to_none=True)
                prediction.depth.mean().backward()
                synchronize(cuda)
                plain_times.append(time.perf_counter() - start)
        step_s, plain_s = statistics.median(step_times[2:]), statistics.median(plain_times[2:])
        print(
            f"one step {1000 * step_s:.0f} ms, plain forward + backward {1000 * plain_s:.0f} ms, "
            f"ratio {step_s / plain_s:.2f}",
            flush=True,
        )
        began = time.perf_counter()
        fitted = adapt(model, camera, frames, config, progress=False)
        whole_s = time.perf_counter() - began
        from raytun3r_plugin.adaptation.config import TEACHER_WEIGHTS
        from raytun3r_plugin.adaptation.losses import LossWeights

        teacher = dataclasses.replace(
            config,
            lr=3e-2,
            guard=False,
            weights=LossWeights(**TEACHER_WEIGHTS),
        )
        began = time.perf_counter()
        taught = adapt(model, camera, frames, teacher, progress=False)
        teacher_s = time.perf_counter() - began
        print(
            f"whole teacher adapt(): {teacher_s:.1f} s for {taught.training_info['steps']} steps "
            f"(teacher targets included), verdict: {taught.training_info['verdict']['summary']}",
            flush=True,
        )
        print(
            f"whole adapt(): {whole_s:.1f} s for {fitted.training_info['steps']} steps "
            f"(matches from the cache), verdict: {fitted.training_info['verdict']['summary']}",
            flush=True,
        )
    RESULTS["timings adapt"] = {
        "render_s": render_s,
        "prepare_s": prepare_s,
        "step_ms": 1000 * step_s,
        "plain_ms": 1000 * plain_s,
        "whole_adapt_s": whole_s,
        "whole_teacher_adapt_s": teacher_s,
        "steps": fitted.training_info["steps"],
    }


if __name__ == "__main__":
    main()
