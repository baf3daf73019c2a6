"""Minimal ArduPilot DataFlash (.bin) writer for simulated logs, in three historical layouts.

A DataFlash log is a stream of records ``A3 95 <type id> <payload>``; FMT records (type 128)
define each message: name, struct format characters and column names.  pymavlink's DFReader reads
the struct characters with ``DFReader.FORMAT_TO_STRUCT`` (used here, so what we write is exactly
what it parses; 'c'/'C'/'e'/'E' are scaled by 100, 'L' by 1e7).

Layouts (column lists as ArduPilot logged them, from the firmware's LogStructure definitions):
* ``timems`` — ArduCopter 3.1/3.2 (2014–2015): TimeMS first column; MAG/MAG2/MAG3
  "TimeMS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ"; CURR (current in cA, voltage in cV);
  PARM "Name,Value" without time; GPS "Status,TimeMS(GPS week ms),Week,...,T(boot ms)".
* ``timeus_split`` — ArduPilot 3.3–4.0: TimeUS; MAG/MAG2/MAG3 with Health,S; BAT without instance.
* ``timeus_instance`` — ArduPilot 4.1+: one MAG message with an instance column I; BAT with Inst;
  PARM "TimeUS,Name,Value,Default".
"""
from __future__ import annotations

import struct
from pathlib import Path

from pymavlink.DFReader import FORMAT_TO_STRUCT

__all__ = ["LAYOUTS", "DataFlashWriter"]

HEAD = b"\xa3\x95"
FMT_ID = 128

LAYOUTS: dict[str, dict[str, tuple[str, str]]] = {
    "attitudes": {      # ATT beside the other estimators' records (AHR2 DCM, XKF1 EKF3 per core, NKF1 EKF2)
        "ATT": ("QccccCCCC", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw"),
        "AHR2": ("QccCfLLffff", "TimeUS,Roll,Pitch,Yaw,Alt,Lat,Lng,Q1,Q2,Q3,Q4"),
        "XKF1": ("QBccCfffffffccce", "TimeUS,C,Roll,Pitch,Yaw,VN,VE,VD,dPD,PN,PE,PD,GX,GY,GZ,OH"),
        "NKF1": ("QBccCfffffffccce", "TimeUS,C,Roll,Pitch,Yaw,VN,VE,VD,dPD,PN,PE,PD,GX,GY,GZ,OH"),
    },
    "timems": {
        "PARM": ("Nf", "Name,Value"),
        "GPS": ("BIHBcLLeeEefI", "Status,TimeMS,Week,NSats,HDop,Lat,Lng,RelAlt,Alt,Spd,GCrs,VZ,T"),
        "ATT": ("IccccCCCC", "TimeMS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw"),
        "MAG": ("Ihhhhhhhhh", "TimeMS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ"),
        "MAG2": ("Ihhhhhhhhh", "TimeMS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ"),
        "MAG3": ("Ihhhhhhhhh", "TimeMS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ"),
        "CURR": ("IhIhhhf", "TimeMS,ThrOut,ThrInt,Volt,Curr,Vcc,CurrTot"),
        "CTUN": ("Ihhhffecchh", "TimeMS,ThrIn,AngBst,ThrOut,DAlt,Alt,BarAlt,DSAlt,SAlt,DCRt,CRt"),
    },
    "timeus_split": {
        "PARM": ("QNf", "TimeUS,Name,Value"),
        "GPS": ("QBIHBcLLefffB", "TimeUS,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,U"),
        "ATT": ("QccccCCCC", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw"),
        "MAG": ("QhhhhhhhhhBI", "TimeUS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health,S"),
        "MAG2": ("QhhhhhhhhhBI", "TimeUS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health,S"),
        "MAG3": ("QhhhhhhhhhBI", "TimeUS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health,S"),
        "BAT": ("Qfffffc", "TimeUS,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp"),
        "CTUN": ("Qffffffefcfhh", "TimeUS,ThI,ABst,ThO,ThH,DAlt,Alt,BAlt,DSAlt,SAlt,TAlt,DCRt,CRt"),
    },
    "timeus_instance": {
        "PARM": ("QNff", "TimeUS,Name,Value,Default"),
        "GPS": ("QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U"),
        "ATT": ("QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF"),
        "MAG": ("QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
        "BAT": ("QBfffffcfBBB", "TimeUS,Inst,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res,RemPct,H,SH"),
        "CTUN": ("Qffffffefffhh", "TimeUS,ThI,ABst,ThO,ThH,DAlt,Alt,BAlt,DSAlt,SAlt,TAlt,DCRt,CRt"),
    },
}


def _struct(fmt: str) -> struct.Struct:
    return struct.Struct("<" + "".join(FORMAT_TO_STRUCT[c][0] for c in fmt))


def _scaled(fmt: str, values: tuple) -> list:
    """Physical values -> stored integers/bytes (the inverse of DFReader's multipliers)."""
    out = []
    for c, v in zip(fmt, values):
        mul = FORMAT_TO_STRUCT[c][1]
        if c in "nNZa":
            out.append(v.encode() if isinstance(v, str) else v)
        elif mul is not None:
            out.append(int(round(float(v) / mul)))
        elif c in "fd":
            out.append(float(v))
        else:
            out.append(int(round(float(v))))
    return out


class DataFlashWriter:
    """Collects records in memory; ``save(path)`` writes the .bin.  ``write(name, *values)`` takes
    physical values in column order (degrees for c/C/e fields, degrees for L lat/lon)."""

    def __init__(self, layout: str) -> None:
        if layout not in LAYOUTS:
            raise ValueError(f"unknown DataFlash layout {layout!r}; choose from {', '.join(LAYOUTS)}")
        self.layout = layout
        self.types: dict[str, tuple[int, str, struct.Struct]] = {}
        self.buf = bytearray()
        fmt_struct = _struct("BBnNZ")
        for k, (name, (fmt, cols)) in enumerate(LAYOUTS[layout].items()):
            st = _struct(fmt)
            type_id = 129 + k
            self.types[name] = (type_id, fmt, st)
            self.buf += HEAD + bytes([FMT_ID]) + fmt_struct.pack(type_id, 3 + st.size, name.encode(),
                                                                 fmt.encode(), cols.encode())
        self.buf = HEAD + bytes([FMT_ID]) + fmt_struct.pack(FMT_ID, 3 + fmt_struct.size, b"FMT", b"BBnNZ",
                                                            b"Type,Length,Name,Format,Columns") + self.buf

    def has(self, name: str) -> bool:
        return name in self.types

    def write(self, name: str, *values) -> None:
        type_id, fmt, st = self.types[name]
        self.buf += HEAD + bytes([type_id]) + st.pack(*_scaled(fmt, values))

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(bytes(self.buf))
        return path
