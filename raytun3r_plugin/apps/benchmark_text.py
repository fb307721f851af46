"""The synthetic benchmark's table header: what was run, what the columns mean, and where the
two targets are met (:func:`~raytun3r_plugin.apps.benchmark.run_benchmark` writes it above the
table in ``results.md`` and the text it returns)."""

from __future__ import annotations

from raytun3r_plugin.apps.sequence_methods import SUPERVISED, ZERO_ADAPTER

#: What the benchmark table's columns and methods mean, under the header's first line.
COLUMN_NOTES = (
    "Each row is the mean over the cell's sequences. rot/trans: relative-pose errors (deg, signed translation direction) on consecutive scored pairs; "
    "d_reproj: px with GT pose and a robust per-pair scale; AbsRel, delta<1.25: per-image median scale, "
    "range depth, sky excluded; coverage: fraction of the fisheye's valid pixels with a depth; adapt_s: wall time of adaptation; "
    "params: trainable parameters (0: nothing fitted); ms_per_frame: wall time of the scored forward passes per frame "
    "(Multi-PH with its resampling and fusion); x_vanilla: that over vanilla's on the same sequence, in the same run; "
    "multi-ph: five pinhole views per frame through the unpatched model, fused back to the fisheye; "
    f"'{ZERO_ADAPTER}': the patch without fitting (parameter-free corrections only); '{SUPERVISED}': the same tables fitted to the "
    "adaptation frames' ground-truth depth (upper bound); gap_closed: the fraction of the mean-AbsRel gap between the zero adapter and the "
    "supervised fit that the self-supervised fit closes; lower_than_X: on how many sequences the metric is below X's.\n"
)


def benchmark_header(
    *,
    network: str,
    size: int,
    sequences: int,
    held_out: bool,
    base_seed: int,
    n_adapt: int,
    n_eval: int,
    fit: str,
    workers: int | None,
    baselines: list[str],
    cells: list[str],
    met: list[str],
    met_zero: list[str],
) -> str:
    """The header: the network, input size (px), sequences and seeds, the fit's settings
    (``fit``, :func:`~raytun3r_plugin.apps.fits.fit_description`), the Ray workers (None: in
    this process), the baselines' method names, :data:`COLUMN_NOTES`, and in how many of
    ``cells`` ("KB4 185 indoor") each target is met (``met``: below vanilla on d_reproj and
    AbsRel; ``met_zero``: below the zero adapter)."""
    return (
        f"Network: {network or 'see model card'}; input {size}x{size} px; {sequences} {'held-out' if held_out else 'development'} sequences per camera and scene "
        f"(seeds {base_seed} + 100 k + 10 camera + scene); per sequence {n_adapt} adaptation frames "
        f"(30 windows, {fit}) and {n_eval} scored frames"
        + (
            f"; {workers} Ray workers of one thread each (timings are one thread's beside the other workers)"
            if workers is not None
            else ""
        )
        + (
            f"; baselines {', '.join(baselines)} fitted on the same frames with the same "
            "objective, windows and steps (raytun3r's tables at zero, no parameter-free corrections)"
            if baselines
            else ""
        )
        + ".\n"
        + COLUMN_NOTES
        + _targets_line(cells, met, met_zero)
    )


def _targets_line(cells: list[str], met: list[str], met_zero: list[str]) -> str:
    """In how many ``cells`` each target is met, and where not."""
    missed = [cell for cell in cells if cell not in met]
    missed_zero = [cell for cell in cells if cell not in met_zero]
    return (
        f"Target (raytun3r's mean d_reproj and AbsRel below vanilla's): met in {len(met)} of {len(met) + len(missed)} cells"
        + (f" (not met: {', '.join(missed)})" if missed else "")
        + f". Target (below '{ZERO_ADAPTER}' on both): met in {len(met_zero)} of {len(met_zero) + len(missed_zero)} cells"
        + (f" (not met: {', '.join(missed_zero)})" if missed_zero else "")
        + ".\n"
    )
