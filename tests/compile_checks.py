"""``torch.compile`` of a patched model, as one check per backbone (tests/test_compile.py and the
contract matrix, tests/test_backbone_contract.py, run it).

Compilations are counted with torch's own counting backend (``CompileCounterWithBackend``:
one count per graph handed to the backend), so a recompilation shows as a count that grows.
"""

from __future__ import annotations

import torch

import raytun3r_plugin as rt
from tests.backbones import CASE, make
from tests.helpers import fisheye, max_relative_difference, outputs, randomise_

#: Compiled against eager output: exact for the "eager" backend; AOT decompositions may
#: round differently (float32).
TOLERANCE = {"eager": 0.0, "aot_eager": 1e-5, "inductor": 1e-4}


def counter(backend: str):
    from torch._dynamo.testing import CompileCounterWithBackend

    torch._dynamo.reset()  # earlier tests' caches must not count (nor fill the recompile limit)
    return CompileCounterWithBackend(backend)


def check_compiled_lifecycle(family: str, backend: str = "eager", components=None) -> dict:
    """Compile a patched ``family`` model and check every documented behaviour of it.

    Matches the eager patched output; repeated calls with one camera and size compile nothing
    more; ``handle.disabled()`` gives upstream's output and ``remove()`` upstream's model (each
    compiles its variant once); a new camera recompiles once and is then stable. Returns the
    compile counts, for the caller's own assertions.
    """
    case = CASE[family]
    net, images = make(family), case.images()
    tolerance = TOLERANCE[backend]
    plain = outputs(net, images)
    height, width = case.size
    camera = fisheye(width, height)
    handle = rt.apply(
        net, camera, randomise_(rt.Adapter.for_model(net, camera)), components=components
    )
    patched = outputs(net, images)
    with handle.disabled():
        assert max_relative_difference(plain, outputs(net, images)) == 0.0

    count = counter(backend)
    compiled = torch.compile(net, backend=count)
    assert max_relative_difference(patched, outputs(compiled, images)) <= tolerance
    counts = {"first": count.frame_count}
    assert counts["first"] > 0
    for _ in range(2):  # one camera, one size: nothing compiles again
        assert max_relative_difference(patched, outputs(compiled, images)) <= tolerance
    assert count.frame_count == counts["first"]

    with handle.disabled():  # upstream's variant: compiled once, then cached
        before = count.frame_count
        assert max_relative_difference(plain, outputs(compiled, images)) <= tolerance
        counts["disabled"] = count.frame_count - before
        before = count.frame_count
        assert max_relative_difference(plain, outputs(compiled, images)) <= tolerance
        assert count.frame_count == before
    before = count.frame_count
    assert max_relative_difference(patched, outputs(compiled, images)) <= tolerance
    assert count.frame_count == before, "back from disabled(): the patched graphs are reused"

    handle.remove()
    assert max_relative_difference(plain, outputs(compiled, images)) <= tolerance

    other = fisheye(width, height, 150.0)
    rt.apply(net, other, randomise_(rt.Adapter.for_model(net, other), seed=3), strict=False)
    expected = outputs(net, images)
    assert max_relative_difference(patched, expected) > 1e-4
    before = count.frame_count
    assert max_relative_difference(expected, outputs(compiled, images)) <= tolerance
    counts["new_camera"] = count.frame_count - before
    before = count.frame_count
    assert max_relative_difference(expected, outputs(compiled, images)) <= tolerance
    assert count.frame_count == before
    rt.remove(net)
    return counts
