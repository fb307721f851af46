"""kill -9 during Adapter.save leaves the old file, the new file or none, and at most one
temporary file, which the next save removes (issue 16).

A child process saves a ~10 MB adapter in a loop, alternating two contents, and is killed with
SIGKILL at a random moment, 20 times. The children are forked from a ``forkserver`` that has
imported torch once, so each kill costs milliseconds, not a torch import.
"""

from __future__ import annotations

import multiprocessing
import os
import random
import re
import signal
import sys

import pytest

pytestmark = pytest.mark.skipif(
    sys.platform == "win32" or "forkserver" not in multiprocessing.get_all_start_methods(),
    reason="needs fork and SIGKILL",
)

KILLS = 20
#: The names a save may leave behind: the adapter and its temporary files.
TEMPORARY = re.compile(r"\.adapter\.safetensors\.raytun3r-tmp-\d+-[0-9a-f]+")


def _adapter(fill: float):
    import torch

    from raytun3r_plugin.adapter import Adapter

    adapter = Adapter("da3", embed_dim=2048, n_r=1024, n_theta=256)  # 10 MB of tables
    with torch.no_grad():
        for table in adapter.pe.values():
            table.fill_(fill)
    return adapter


def _save_forever(path: str, ready) -> None:  # runs in the child
    adapters = [_adapter(1.0), _adapter(2.0)]
    ready.set()
    for turn in range(10**9):
        adapters[turn % 2].save(path)


def _fill_of(path) -> float:
    from raytun3r_plugin.adapter import Adapter

    adapter = Adapter.load(path)  # complete and valid, or this raises
    values = {float(v) for table in adapter.pe.values() for v in table.detach().unique()}
    assert len(values) == 1, values
    return values.pop()


def _leftovers(folder) -> tuple[list[str], list[str]]:
    names = sorted(p.name for p in folder.iterdir())
    temporaries = [name for name in names if TEMPORARY.fullmatch(name)]
    others = [name for name in names if name not in temporaries and name != "adapter.safetensors"]
    return temporaries, others


def test_kill_during_save_leaves_old_new_or_nothing_and_one_temporary_at_most(tmp_path):
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["torch", "safetensors.torch", "raytun3r_plugin.adapter"])
    path = tmp_path / "adapter.safetensors"
    rng = random.Random(16)
    seen_temporary = 0
    for _kill in range(KILLS):
        ready = context.Event()
        child = context.Process(target=_save_forever, args=(str(path), ready), daemon=True)
        child.start()
        assert ready.wait(60), "the saving child did not start"
        # A save takes some 30 ms: a random moment within the first few saves.
        child.join(rng.uniform(0.0, 0.15))
        os.kill(child.pid, signal.SIGKILL)
        child.join(10)
        assert child.exitcode == -signal.SIGKILL

        temporaries, others = _leftovers(tmp_path)
        assert not others, others  # no temporary file of another writer (safetensors' own)
        assert len(temporaries) <= 1, temporaries
        seen_temporary += len(temporaries)
        if path.exists():
            assert _fill_of(path) in (1.0, 2.0)
        if temporaries:
            # A save of another file in the folder sweeps the killed writer's temporary too.
            _adapter(4.0).save(tmp_path / "other.safetensors")
            assert _leftovers(tmp_path)[0] == [], "a stray temporary survived a save beside it"
            (tmp_path / "other.safetensors").unlink()

    # The next save removes the killed writers' temporary file.
    _adapter(3.0).save(path)
    assert _leftovers(tmp_path) == ([], [])
    assert _fill_of(path) == 3.0
    print(f"{KILLS} kills, {seen_temporary} left a temporary file")
