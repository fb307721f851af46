"""Robustness campaign: fuzzed adapter and calibration files, and saves killed mid-write.

Counts, over generated inputs, the failure classes that the library promises never to have:

- ``other exceptions``: a reader raised something that is not a ``Raytun3rError``;
- ``hangs``: one read took more than ``--hang-s`` seconds (5 by default);
- ``accepted, fail later``: a file was accepted, but its camera does not round-trip or the
  patched forward of a small DA3 network with it is not finite (or raises);
- ``refused, model changed``: an adapter that ``apply`` refused left the model's state different;
- ``leaks``: after ``--kills`` SIGKILLs during ``Adapter.save`` of one path and one more
  save, a temporary file is left, or the file on disk is neither the old nor the new adapter.

Adapter files are valid adapters with one mutation each (tests/adapter_generators.py);
calibration variants are valid Kalibr/Basalt/CamOdoCal/COLMAP/raytun3r calibrations with one
mutation each (tests/calibration_generators.py). Both are seeded, so a run reproduces.

    python -m benchmarks.robustness_campaign [--adapters 1000] [--calibrations 10000] [--kills 60]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import random
import signal
import tempfile
import time
from collections import Counter
from contextlib import contextmanager
from pathlib import Path

import torch

import raytun3r_plugin as rt
from raytun3r_plugin.errors import Raytun3rError


class Hang(Exception):
    pass


@contextmanager
def time_limit(seconds: float):
    def on_alarm(signum, frame):
        raise Hang

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _state(net: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {key: value.clone() for key, value in net.state_dict().items()}


def camera_works(camera, net, images) -> str | None:
    """None if ``camera`` passes its checks again (round trip included, uncached) and drives a
    finite patched forward of a small DA3 network at the test size, else the reason."""
    from raytun3r_plugin.cameras import validate

    try:
        validate(camera)  # the construction checks again, uncached: domain, round trip, sizes
        small = camera.resized(images.shape[-1], images.shape[-2])
        with rt.apply(net, small), torch.no_grad():
            depth = rt.predict(net, images).depth
        if not bool(torch.isfinite(depth).all()):
            return "patched forward is not finite"
    except Raytun3rError as error:
        # A clear refusal at resize or apply time (e.g. no patch inside the lens at 56 px) is
        # counted apart: the model is untouched and the user told why; it is not a break.
        return f"refused later: {type(error).__name__}: {str(error)[:80]}"
    except Exception as error:  # the campaign counts, it does not stop
        return f"{type(error).__name__} later: {str(error)[:80]}"
    return None


def _count_later(outcomes: Counter, examples: dict, problem: str | None, label: str) -> None:
    if problem is None:
        return
    kind = (
        "accepted, refused cleanly later"
        if problem.startswith("refused later")
        else "accepted, fail later"
    )
    outcomes[kind] += 1
    examples.setdefault(kind, f"{label}{problem}")


def read_counted(read, path: Path, hang_s: float, outcomes: Counter, examples: dict, label: str):
    """``read(path)``, counting the outcome; returns ``(value or None, seconds)`` and removes
    the file."""
    started = time.perf_counter()
    try:
        with time_limit(hang_s):
            value = read(path)
    except Hang:
        outcomes["hangs"] += 1
        value = None
    except Raytun3rError:
        outcomes["refused"] += 1
        value = None
    except Exception as error:  # what the campaign exists to find
        outcomes["other exceptions"] += 1
        examples.setdefault(type(error).__name__, f"{label}: {str(error)[:120]}")
        value = None
    else:
        outcomes["accepted"] += 1
    finally:
        path.unlink(missing_ok=True)
    return value, time.perf_counter() - started


def adapter_campaign(count: int, seed: int, hang_s: float, net, images, folder: Path) -> dict:
    from tests.adapter_generators import adapter_bytes, mutate, valid_adapter

    rng = random.Random(seed)
    outcomes: Counter[str] = Counter()
    examples: dict[str, str] = {}
    reference = _state(net)
    slowest = 0.0
    for index in range(count):
        template = valid_adapter(rng)
        if index % 2:  # half the files fit the network, so apply and forward are reached
            fitting = rt.Adapter.for_model(net, template.camera)
            fitting.load_state_dict(
                {k: torch.randn_like(v) * 0.05 for k, v in fitting.state_dict().items()}
            )
            template = fitting
        path = folder / f"adapter-{index}.safetensors"
        path.write_bytes(mutate(rng, adapter_bytes(template)))
        adapter, seconds = read_counted(
            rt.Adapter.load, path, hang_s, outcomes, examples, path.name
        )
        slowest = max(slowest, seconds)
        if adapter is None:
            continue
        camera = adapter.camera
        if camera is None:
            continue
        problem = camera_works(camera, net, images)
        if problem is not None:
            _count_later(outcomes, examples, problem, f"{path.name}: ")
            continue
        try:
            with rt.apply(net, camera.resized(56, 56), adapter, strict=False), torch.no_grad():
                depth = rt.predict(net, images).depth
            if not bool(torch.isfinite(depth).all()):
                outcomes["accepted, fail later"] += 1
                examples.setdefault("fail later", "adapter forward not finite")
        except Raytun3rError:
            outcomes["refused by apply"] += 1
            after = net.state_dict()
            if any(not torch.equal(reference[k], after[k]) for k in reference):
                outcomes["refused, model changed"] += 1
        except Exception as error:
            outcomes["accepted, fail later"] += 1
            examples.setdefault("fail later", f"{type(error).__name__}: {str(error)[:80]}")
    return {"files": count, "outcomes": dict(outcomes), "slowest_s": slowest, "examples": examples}


def calibration_campaign(count: int, seed: int, hang_s: float, net, images, folder: Path) -> dict:
    from raytun3r_plugin.cameras import formats
    from tests.calibration_generators import mutate, valid_calibrations

    rng = random.Random(seed)
    outcomes: Counter[str] = Counter()
    per_format: Counter[str] = Counter()
    examples: dict[str, str] = {}
    slowest = 0.0
    checked: dict[tuple, str | None] = {}
    variants = valid_calibrations(rng, max(1, count // 10))
    for index in range(count):
        name, text = variants[index % len(variants)]
        data = text.encode() if index < len(variants) else mutate(rng, text)
        suffix = {"colmap": ".txt", "raytun3r": ".json"}.get(name, ".yaml")
        path = folder / f"calibration-{index}{suffix}"
        path.write_bytes(data)
        per_format[name] += 1
        camera, seconds = read_counted(formats.load, path, hang_s, outcomes, examples, name)
        slowest = max(slowest, seconds)
        if camera is None:
            continue
        key = camera.key()
        if key not in checked:
            checked[key] = camera_works(camera, net, images)
        _count_later(outcomes, examples, checked[key], f"{name}: ")
    return {
        "variants": count,
        "formats": dict(per_format),
        "outcomes": dict(outcomes),
        "distinct accepted cameras checked": len(checked),
        "slowest_s": slowest,
        "examples": examples,
    }


def _save_forever(path: str, ready) -> None:  # the child of the kill campaign
    from raytun3r_plugin.adapter import Adapter

    adapters = []
    for fill in (1.0, 2.0):
        adapter = Adapter("da3", embed_dim=2048, n_r=1024, n_theta=256)
        with torch.no_grad():
            for table in adapter.pe.values():
                table.fill_(fill)
        adapters.append(adapter)
    ready.set()
    for turn in range(10**9):
        adapters[turn % 2].save(path)


def kill_campaign(kills: int, seed: int, folder: Path) -> dict:
    from raytun3r_plugin.adapter import Adapter

    rng = random.Random(seed)
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["torch", "raytun3r_plugin.adapter"])
    path = folder / "adapter.safetensors"
    outcomes: Counter[str] = Counter()
    for _ in range(kills):
        ready = context.Event()
        child = context.Process(target=_save_forever, args=(str(path), ready))
        child.start()
        ready.wait(60)
        time.sleep(rng.uniform(0.0, 0.3))
        os.kill(child.pid, signal.SIGKILL)
        child.join()
        if path.exists():
            try:
                fills = {float(t.detach().unique()[0]) for t in Adapter.load(path).pe.values()}
                outcomes["whole file" if fills in ({1.0}, {2.0}) else "torn file"] += 1
            except Raytun3rError:
                outcomes["torn file"] += 1
        temporaries = [p for p in folder.iterdir() if p.name != path.name]
        outcomes["max temporaries after a kill"] = max(
            outcomes["max temporaries after a kill"], len(temporaries)
        )
    Adapter("da3", embed_dim=8).save(path)
    left = [p.name for p in folder.iterdir() if p.name != path.name]
    outcomes["temporaries after the next save"] = len(left)
    return {"kills": kills, "outcomes": dict(outcomes)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--adapters", type=int, default=1000)
    parser.add_argument("--calibrations", type=int, default=10000)
    parser.add_argument("--kills", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--hang-s", type=float, default=5.0)
    parser.add_argument("--json", type=Path, help="also write the counts here")
    args = parser.parse_args(argv)

    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    torch.manual_seed(args.seed)
    net = build_tiny_network(seed=0)
    images = torch.rand(2, 3, 56, 56)
    report: dict = {"seed": args.seed}
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        report["adapters"] = adapter_campaign(
            args.adapters, args.seed, args.hang_s, net, images, Path(folder)
        )
    if args.calibrations:
        with tempfile.TemporaryDirectory() as folder:
            report["calibrations"] = calibration_campaign(
                args.calibrations, args.seed + 1, args.hang_s, net, images, Path(folder)
            )
    if args.kills:
        with tempfile.TemporaryDirectory() as folder:
            report["saves"] = kill_campaign(args.kills, args.seed + 2, Path(folder))
    report["wall_s"] = round(time.perf_counter() - started, 1)
    print(json.dumps(report, indent=2, sort_keys=True))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2, sort_keys=True))
    return report


if __name__ == "__main__":
    main()
