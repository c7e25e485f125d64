"""The runtime's packed buffers: every offset constant is a declared slot, no two overlap."""

from __future__ import annotations

import pytest

import controller.runtime.kernels as kernels
from controller.runtime.layout import BufferLayout

#: buffer layout -> (prefix of its offset constants, the constants that give its size)
LAYOUTS = {
    "MAT": ("M_", ("MAT_COLS",)),
    "VEC": ("V_", ("VEC_COLS",)),
    "ST": ("S_", ("ST_COLS",)),
    "FV": ("F_", ("FV_HEAD",)),
    "IV": ("I_", ("IV_HEAD", "IV_ACT")),
}


@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_every_offset_constant_is_its_own_slot(name: str) -> None:
    layout: BufferLayout = getattr(kernels, name)
    prefix, size_names = LAYOUTS[name]
    constants = {k: v for k, v in vars(kernels).items()
                 if k.startswith(prefix) and isinstance(v, int)}
    starts = [s.offset for s in layout.slots]
    assert sorted(constants.values()) == starts, "a constant that is not a declared slot"
    for k in size_names:
        assert getattr(kernels, k) == layout.size


@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_slots_tile_the_buffer_without_overlap(name: str) -> None:
    layout: BufferLayout = getattr(kernels, name)
    covered = [0] * layout.size
    for s in layout.slots:
        assert s.size >= 1
        for i in range(s.offset, s.end):
            covered[i] += 1
    assert covered == [1] * layout.size


def test_a_slot_needs_an_entry() -> None:
    with pytest.raises(ValueError, match="at least one entry"):
        BufferLayout("x").slot(0)
