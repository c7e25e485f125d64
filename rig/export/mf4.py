"""A run as ASAM MDF 4.10 (asammdf): one channel group per tick topic (acquisition
name = the topic, one channel per field, SI unit in the channel's unit) and the CAN bus
log as bus-logging channel groups after the ASAM MDF bus logging standard
(``CAN_DataFrame`` with ``.BusChannel``, ``.ID``, ``.IDE``, ``.DLC``, ``.DataLength``,
``.DataBytes``, ``.Dir``; ``CAN_ErrorFrame`` for error frames; source = CAN bus, the
channel group flagged as bus event), the layout python-can's ``can.io.MF4Writer``
writes, so that ``can.io.MF4Reader``, asammdf's ``extract_bus_logging`` and CANape
decode it with ``rig/wire/rig.dbc`` (attached to the file).  Written in one vectorised
append per group (``MF4Writer`` takes a call per frame).

Time: seconds since the run's first item (:attr:`RunTables.t0_ns`); the header's start
time is that instant on the wall clock."""

from __future__ import annotations

from datetime import UTC, datetime
from hashlib import md5
from pathlib import Path
from typing import Any, Final

import numpy as np
from asammdf import MDF, Signal, Source
from asammdf.blocks.v4_constants import BUS_TYPE_CAN, SOURCE_BUS

from rig.export.tables import CAN_DATA_BYTES, CanLog, RunTables
from rig.wire.generate import DBC_PATH

__all__ = ["BUS_CHANNEL", "Mf4Stream", "write_mf4"]

#: ``CAN_DataFrame.BusChannel`` of every frame (the rig has one bus)
BUS_CHANNEL: Final = 1
#: ``.Dir`` values (ASAM MDF bus logging; python-can: 0 = received)
_DIR_RX, _DIR_TX = 0, 1


def _frame_dtype(event: str) -> np.dtype[Any]:
    return np.dtype([(f"{event}.{name}", fmt) for name, fmt in (
        ("BusChannel", "<u1"), ("ID", "<u4"), ("IDE", "<u1"), ("DLC", "<u1"),
        ("DataLength", "<u1"), ("DataBytes", f"({CAN_DATA_BYTES},)u1"), ("Dir", "<u1"))])


def _bus_signal(can: CanLog, rows: np.ndarray[Any, Any], event: str,
                t_s: np.ndarray[Any, Any], attachment: tuple[bytes, Path, bytes]) -> Signal:
    samples = np.zeros(int(rows.sum()), dtype=_frame_dtype(event))
    samples[f"{event}.BusChannel"] = BUS_CHANNEL
    samples[f"{event}.ID"] = can.arbitration_id[rows]
    samples[f"{event}.IDE"] = can.is_extended_id[rows]
    samples[f"{event}.DLC"] = can.dlc[rows]
    samples[f"{event}.DataLength"] = can.dlc[rows]
    samples[f"{event}.DataBytes"] = can.data[rows]
    samples[f"{event}.Dir"] = np.where(can.is_rx[rows], _DIR_RX, _DIR_TX)
    source = Source(name="CAN1", path="CAN1", comment="rig CAN bus (rig/wire/rig.dbc)",
                    source_type=SOURCE_BUS, bus_type=BUS_TYPE_CAN)
    return Signal(samples=samples, timestamps=t_s[rows], name=event, source=source,
                  attachment=attachment, comment=f"{event} of /can/rx and /can/tx")


class Mf4Stream:
    """An MF4 file built batch by batch (:meth:`add`: the first batch of a group
    appends it, later ones extend it), written by :meth:`save`."""

    def __init__(self, start_wall_ns: int, *, comment: str = "") -> None:
        self.mdf = MDF(version="4.10")
        self.mdf.header.start_time = datetime.fromtimestamp(start_wall_ns * 1e-9, UTC)
        self.mdf.header.comment = comment or "rig export"
        self.groups: dict[str, int] = {}     # acquisition name -> group index
        dbc = DBC_PATH.read_bytes()
        self._attachment = (dbc, Path(DBC_PATH.name), md5(dbc).digest())

    def add(self, tables: RunTables) -> None:
        for table in tables.topics:
            t_s = tables.seconds(table.t_ns)
            if self._extend(table.topic, [t_s, table.tick, *table.columns.values()]):
                continue
            sigs = [Signal(samples=table.tick, timestamps=t_s, name="tick",
                           comment="loop tick number")]
            sigs += [Signal(samples=col, timestamps=t_s, name=name, unit=unit)
                     for (name, col), unit in zip(table.columns.items(),
                                                  table.units.values(), strict=True)]
            self._append(table.topic, sigs, table.topic)
        can = tables.can
        t_s = tables.seconds(can.t_ns)
        for event, rows in (("CAN_DataFrame", ~can.is_error_frame),
                            ("CAN_ErrorFrame", can.is_error_frame)):
            if not rows.any():
                continue
            sig = _bus_signal(can, rows, event, t_s, self._attachment)
            if not self._extend(event, [sig.timestamps, sig.samples]):
                self._append(event, [sig], f"{event} /can/rx + /can/tx")

    def _append(self, name: str, sigs: list[Signal], comment: str) -> None:
        self.mdf.append(sigs, acq_name=name, comment=comment)
        self.groups[name] = len(self.mdf.groups) - 1

    def _extend(self, name: str, arrays: list[np.ndarray[Any, Any]]) -> bool:
        index = self.groups.get(name)
        if index is None:
            return False
        self.mdf.extend(index, [(a, None) for a in arrays])
        return True

    def save(self, path: str | Path) -> None:
        """Write the new MF4 file ``path`` (the caller stages and renames)."""
        self.mdf.save(Path(path), overwrite=True, compression=2)

    def close(self) -> None:
        self.mdf.close()


def write_mf4(tables: RunTables, path: str | Path, *, comment: str = "") -> None:
    """Write ``tables`` to the new MF4 file ``path`` (the caller stages and renames)."""
    out = Mf4Stream(tables.start_wall_ns, comment=comment)
    try:
        out.add(tables)
        out.save(path)
    finally:
        out.close()
