"""apply is all-or-nothing for any exception, KeyboardInterrupt included, at any point (issue 16).

A failure is injected at every step that changes the model: before each undo record, before and
after each attribute write, in the handle's construction, and before and after its registration
on the model. After each one the model must be bit-identical to before (state, attributes and
the very objects they hold, outputs), ``handle_of`` must be None, and the model must patch and
unpatch normally. An interrupt just after the global lock is taken must not leave it held.
"""

from __future__ import annotations

import threading

import pytest

import raytun3r_plugin as rt
from raytun3r_plugin import patching
from tests.backbones import CASE, make
from tests.helpers import (
    assert_same_snapshot,
    fisheye,
    max_relative_difference,
    outputs,
    randomise_,
    snapshot,
)

DA3 = CASE["da3"]


def _camera():
    height, width = DA3.size
    return fisheye(width, height)


def _objects(model) -> dict[str, dict[str, object]]:
    """Every module's instance attributes (the objects themselves, kept alive here)."""
    return {name: dict(vars(module)) for name, module in model.named_modules()}


def _assert_same_objects(model, before) -> None:
    now = _objects(model)
    assert now.keys() == before.keys()
    for name, attributes in before.items():
        assert now[name].keys() == attributes.keys(), name
        stray = [key for key, value in attributes.items() if now[name][key] is not value]
        assert not stray, f"{name}: {stray} replaced"


class _Injected:
    """Raises ``error`` at the ``at``-th call of a fault point, once."""

    def __init__(self, error: type[BaseException], at: int):
        self.error, self.at, self.calls = error, at, 0

    def tick(self) -> None:
        self.calls += 1
        if self.calls == self.at:
            raise self.error("injected failure")


def _inject(monkeypatch, point: str, fault: _Injected) -> None:
    """Install ``fault`` at ``point`` of patching.py (see POINTS)."""
    real_record, real_write, real_register = patching._record, patching._write, patching._register
    real_handle_init = patching.RaytunHandle.__init__

    if point == "record":

        def record(installed, item):
            fault.tick()
            real_record(installed, item)

        monkeypatch.setattr(patching, "_record", record)
    elif point in ("before write", "after write"):

        def write(owner, attribute, value):
            if point == "before write":
                fault.tick()
            real_write(owner, attribute, value)
            if point == "after write":
                fault.tick()

        monkeypatch.setattr(patching, "_write", write)
    elif point == "handle":

        def handle_init(self, *args, **kwargs):
            real_handle_init(self, *args, **kwargs)
            fault.tick()

        monkeypatch.setattr(patching.RaytunHandle, "__init__", handle_init)
    else:

        def register(model, handle):
            if point == "before register":
                fault.tick()
            real_register(model, handle)
            if point == "after register":
                fault.tick()

        monkeypatch.setattr(patching, "_register", register)


POINTS = ("record", "before write", "after write", "handle", "before register", "after register")


@pytest.fixture(scope="module")
def setup():
    net = make("da3")
    images = DA3.images()
    adapter = randomise_(rt.Adapter.for_model(net))
    reference = outputs(net, images)
    with rt.apply(net, _camera(), adapter):
        patched = outputs(net, images)
    # The number of attribute writes of a real apply of this model: one per install step.
    counted = {"n": 0}
    real_write = patching._write

    def counting(*args):
        counted["n"] += 1
        real_write(*args)

    patching._write = counting
    try:
        rt.apply(net, _camera(), adapter).remove()
    finally:
        patching._write = real_write
    assert counted["n"] >= 5, counted  # patch embedding, RoPE, attention, heads...
    return net, images, adapter, reference, patched, counted["n"]


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_a_failure_at_any_step_leaves_the_model_as_it_was(setup, error, monkeypatch):
    net, images, adapter, reference, patched, steps = setup
    snap, objects = snapshot(net), _objects(net)
    seen = 0
    for point in POINTS:
        for at in range(1, (steps if "write" in point or point == "record" else 1) + 1):
            fault = _Injected(error, at)
            with monkeypatch.context() as patch:
                _inject(patch, point, fault)
                with pytest.raises(error, match="injected"):
                    rt.apply(net, _camera(), adapter)
            assert fault.calls == at, (point, at)
            where = f"{error.__name__} at {point} #{at}"
            assert rt.handle_of(net) is None, where
            assert_same_snapshot(net, snap)
            _assert_same_objects(net, objects)
            seen += 1
            # Unpatched outputs are upstream's, and the model patches and unpatches normally.
            assert max_relative_difference(reference, outputs(net, images)) == 0.0, where
            with rt.apply(net, _camera(), adapter) as handle:
                assert rt.handle_of(net) is handle, where
                assert max_relative_difference(patched, outputs(net, images)) == 0.0, where
            assert rt.handle_of(net) is None, where
            assert_same_snapshot(net, snap)
            _assert_same_objects(net, objects)
    assert seen == 3 * steps + 3


class _InterruptedLock:
    """The global lock, but the first acquisition is interrupted just after it succeeds."""

    def __init__(self, lock):
        self._lock, self._interrupted = lock, False

    def _interrupt(self) -> None:
        if not self._interrupted:
            self._interrupted = True
            raise KeyboardInterrupt("injected failure")

    def acquire(self, *args, **kwargs):
        acquired = self._lock.acquire(*args, **kwargs)
        self._interrupt()
        return acquired

    def __enter__(self):
        self.acquire()
        return self

    def __exit__(self, *exc):
        self._lock.release()

    def release(self):
        self._lock.release()

    def _is_owned(self):
        return self._lock._is_owned()


def test_an_interrupt_just_after_taking_the_lock_does_not_leave_it_held(setup, monkeypatch):
    net, images, adapter, reference, patched, _steps = setup
    monkeypatch.setattr(patching, "_LOCK", _InterruptedLock(patching._LOCK))
    with pytest.raises(KeyboardInterrupt, match="injected"):
        rt.apply(net, _camera(), adapter)
    assert rt.handle_of(net) is None
    done = threading.Event()
    failures: list[BaseException] = []

    def other_thread():
        try:
            with rt.apply(net, _camera(), adapter):
                pass
        except BaseException as error:  # reported below
            failures.append(error)
        done.set()

    worker = threading.Thread(target=other_thread, daemon=True)
    worker.start()
    assert done.wait(5.0), "a second apply in another thread hangs on the global lock"
    assert not failures, failures
    assert rt.handle_of(net) is None
    assert max_relative_difference(reference, outputs(net, images)) == 0.0


class _InterruptedRelease(_InterruptedLock):
    """The global lock, but its first release is interrupted, before or after it takes effect:
    the end of ``apply`` (issue: an interrupt inside its final lock release)."""

    def __init__(self, lock, after: bool):
        super().__init__(lock)
        self._after = after

    def acquire(self, *args, **kwargs):
        return self._lock.acquire(*args, **kwargs)

    def release(self):
        if not self._after:
            self._interrupt()
        self._lock.release()
        if self._after:
            self._interrupt()


@pytest.mark.parametrize("after", [False, True], ids=["before", "after"])
def test_an_interrupt_inside_the_final_release_leaves_the_model_and_the_lock_clean(
    setup, monkeypatch, after
):
    net, images, adapter, reference, patched, _steps = setup
    snap = snapshot(net)
    lock = _InterruptedRelease(patching._LOCK, after)
    monkeypatch.setattr(patching, "_LOCK", lock)
    with pytest.raises(KeyboardInterrupt, match="injected"):
        rt.apply(net, _camera(), adapter)
    assert lock._interrupted
    assert rt.handle_of(net) is None
    assert not lock._is_owned(), "the interrupted thread still holds the global lock"
    assert_same_snapshot(net, snap)
    assert max_relative_difference(reference, outputs(net, images)) == 0.0
    # The lock is free for another thread, and the model patches normally again.
    done = threading.Event()

    def other_thread():
        with rt.apply(net, _camera(), adapter):
            pass
        done.set()

    threading.Thread(target=other_thread, daemon=True).start()
    assert done.wait(5.0), "a second apply in another thread hangs on the global lock"
    with rt.apply(net, _camera(), adapter):
        assert max_relative_difference(patched, outputs(net, images)) == 0.0
    assert rt.handle_of(net) is None
