"""PyPose 0.9.5 under torch ≥ 2.14: its cumulative-product scan fails for lengths that are not
powers of two; the benchmarks that run PyPose (``peers.py``, ``learning.py``) patch it with
the same scan, and say so."""


def fix_pypose_cumops():
    """Make PyPose's cumulative product run under this torch, if it does not; returns the
    reason when it was patched, else ``None``.

    PyPose 0.9.5's ``pypose.basics.ops.cumops_`` (the scan behind ``cumprod``, which
    ``IMUPreintegrator.integrate`` calls) steps over ``i`` in
    ``2 ** torch.arange(math.log2(L) + 1, dtype=torch.int64)``; torch 2.14 gives that range
    ``ceil(log2(L) + 1)`` elements, so the last ``i`` exceeds ``L`` and
    ``torch.arange(i, L)`` raises "upper bound and lower bound inconsistent with step sign"
    for every ``L`` that is not a power of two (``L = F + 1 = 17`` here). The replacement is
    the same Hillis-Steele scan over ``i = 1, 2, 4, … < L`` (the powers the loop means;
    with ``i ≥ L`` a step has nothing to do), the same operations in the same order."""
    import torch
    from pypose.basics import ops

    try:
        ops.cumops(torch.ones(17, 1), 0, lambda a, b: a * b)
        return None
    except RuntimeError as e:
        reason = (
            f"pypose.basics.ops.cumops_ fails under torch {torch.__version__} ({e}); "
            "replaced by the same scan over the powers of two below the length"
        )

    def cumops_(input, dim, op):
        L, v = input.shape[dim], input
        i = 1
        while i < L:
            index = torch.arange(i, L, device=v.device, dtype=torch.int64)
            v.index_copy_(
                dim, index, op(v.index_select(dim, index - i), v.index_select(dim, index))
            )
            i *= 2
        return v

    ops.cumops_ = cumops_
    ops.cumops(torch.ones(17, 1), 0, lambda a, b: a * b)  # runs now
    return reason
