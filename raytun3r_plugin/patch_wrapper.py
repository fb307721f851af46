"""The callable installed in place of one upstream method on one owner instance.

Modelled on accelerate's ``add_hook_to_module``: the wrapper holds its owner by weak reference
and looks the original method up at call time, so it never pins the model, a deep copy rebinds
to the copied owner, and a method patched by someone else after us still runs.
:mod:`raytun3r_plugin.patching` installs and removes these wrappers.
"""

from __future__ import annotations

import copy
import functools
import inspect
import threading
import types
import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from raytun3r_plugin.errors import NotAppliedError, PatchedCopyError

if TYPE_CHECKING:
    from raytun3r_plugin.patch_state import PatchState
    from raytun3r_plugin.registry import PatchTarget

#: Class attribute that identifies an installed raytun3r wrapper.
WRAPPER_MARK = "__raytun3r_wrapper__"


class _NotSet:
    """Marks a wrapper whose owner had no instance attribute of its own (the class method runs)."""

    def __repr__(self) -> str:
        return "<not set>"

    def __deepcopy__(self, memo: dict) -> _NotSet:
        return self


#: The ``previous`` of a wrapper whose owner had no instance attribute of its own.
NOT_SET = _NotSet()


class PatchWrapper:
    """The callable installed in place of one upstream method on one owner instance.

    It holds the owner by weak reference and resolves the original method on every call (the
    class method bound to the owner, or the instance attribute it shadowed), so it never pins
    the model and a deep copy rebinds to the copied owner; the behaviour comes from
    ``target.build(owner, state)`` and is rebuilt for a copy. ``__wrapped__``, ``__name__`` and
    ``__signature__`` are the original's, so ``inspect`` sees the upstream method.
    """

    __raytun3r_wrapper__ = True  # the attribute WRAPPER_MARK names

    def __init__(
        self,
        owner: Any,
        target: PatchTarget,
        state: PatchState,
        previous: Any = NOT_SET,
        *,
        build: bool = True,
    ):
        self._owner = weakref.ref(owner)
        self._target = target
        self._state = state
        self._previous = previous
        self._lock = threading.Lock()
        self._behaviour = target.build(owner, state) if build else None
        named = getattr(type(owner), target.attribute) if previous is NOT_SET else previous
        self.__name__ = getattr(named, "__name__", target.attribute)
        self.__qualname__ = getattr(named, "__qualname__", target.attribute)
        self.__doc__ = getattr(named, "__doc__", None)
        self.__module__ = getattr(named, "__module__", type(owner).__module__)

    def _original(self, bound: bool = False) -> Callable:
        """Upstream's method for this owner: the class function with the owner as a partial
        (what a call runs), or, with ``bound``, a bound method (what introspection sees)."""
        owner = self._owner()
        if owner is None:
            raise NotAppliedError(
                f"the module owning {self._target.attribute} was garbage-collected"
            )
        if self._previous is not NOT_SET:
            return self._previous
        method = getattr(type(owner), self._target.attribute)
        if isinstance(method, types.FunctionType) and not bound:
            # Not ``method.__get__(owner)``: torch.compile rebuilds a bound method after a graph
            # break as ``owner.<attribute>``, which finds this wrapper again (endless recursion).
            return functools.partial(method, owner)
        return method.__get__(owner, type(owner))

    def _built(self) -> Callable:
        with self._lock:
            if self._behaviour is None:
                self._behaviour = self._target.build(self._owner(), self._state)
            return self._behaviour

    def __call__(self, *args, **kwargs):
        behaviour = self._behaviour or self._built()
        return behaviour(self._original(), *args, **kwargs)

    @property
    def __wrapped__(self) -> Callable:
        return self._original(bound=True)

    @property
    def __signature__(self) -> inspect.Signature:
        return inspect.signature(self._original(bound=True))

    def __deepcopy__(self, memo: dict) -> PatchWrapper:
        state = copy.deepcopy(self._state, memo)  # refuses a copy of only a part of the model
        owner = copy.deepcopy(self._owner(), memo)  # already in memo: the copy being built
        # The copied owner is still empty here (deepcopy is filling its __dict__), so the
        # behaviour, which may read it, is built on the copy's first call.
        twin = PatchWrapper(
            owner, self._target, state, copy.deepcopy(self._previous, memo), build=False
        )
        memo[id(self)] = twin
        return twin

    def __reduce_ex__(self, protocol):
        raise PatchedCopyError(
            "a patched model cannot be pickled: call handle.remove() first (apply() again after loading)"
        )

    def __repr__(self) -> str:
        owner = self._owner()
        where = type(owner).__qualname__ if owner is not None else "<freed>"
        return f"<raytun3r wrapper of {where}.{self._target.attribute}>"
