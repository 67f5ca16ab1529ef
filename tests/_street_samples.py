"""Synthetic street samples at SemanticKITTI's classes and 10 fused scans, shared (built once per process) by the
tests that only read them: tests/test_data.py (every class occurs) and tests/test_rectify.py (moving cars' traces).
Both tests carry ``xdist_group("street")`` so that one worker builds the samples once."""

from __future__ import annotations

from functools import lru_cache

from conftest import TINY_DATA
from distilkit.data.params import SyntheticParams

# 64 x 64 x 8 voxels of 0.8 m, the completion labels fused from the current scan and the next 10 (32 beams x 512
# azimuth steps): seeds 2 and 3 together hold all 19 classes, and each has moving cars with traces
STREET = SyntheticParams(**TINY_DATA).model_copy(update={"scale": 4, "beams": 32, "azimuth_steps": 512,
                                                          "gt_frames": 10, "input_frames": 1})
SEEDS = (2, 3)


@lru_cache(maxsize=None)
def street_sample(seed: int) -> dict:
    """``make_sample(seed, STREET)`` (callers must not modify its arrays)."""
    from distilkit.data.synthetic import make_sample

    return make_sample(seed, STREET)
