"""A C3D parser for the processor types ezc3d 1.7 refuses (SGI/MIPS, big-endian).

C3D files record the processor that wrote them in byte 4 of the parameter section: 84 Intel
(little-endian integers, IEEE floats), 85 DEC (little-endian integers, VAX F-floating floats),
86 SGI/MIPS (big-endian integers, big-endian IEEE floats). ezc3d reads 84 and 85 but raises
"MIPS processor type not supported" on 86, so :func:`read_c3d_dict` parses the file itself.
It reads all three (the Intel and DEC paths exist to check this parser against ezc3d).

Layout (C3D User Guide, "The C3D file format"):

- Header, block 1 (512 bytes), 16-bit words: word 1 = parameter block (byte) + key 0x50,
  2 points, 3 analog samples per frame (all channels), 4 first frame (1-based), 5 last frame,
  6 interpolation gap, 7-8 scale (float; < 0 = float data), 9 data start block,
  10 analog samples per channel per frame, 11-12 frame rate (float).
- Parameter section: 4 bytes (reserved, reserved, block count, processor type), then records:
  name length (int8, negative = locked), group id (int8, negative = group record), name,
  offset to the next record (int16), and for a parameter: type (int8: -1 char, 1 byte,
  2 int16, 4 float32), dimension count (uint8), dimensions (uint8 each), the data in
  column-major order, then a description (length byte + text).
- Data: per frame, per point x, y, z and a fourth word (int16 data: int16 words scaled by
  ``POINT:SCALE``; float data: float32 already in ``POINT:UNITS``), then the analog samples.
  The fourth word, as an int16 (float data: a float holding that integer): negative = invalid
  point, high byte = residual / |scale|, bits 0-6 of the low byte = the cameras that saw the
  point (the reading of ezc3d and of DART's ``c3d_frameSI_t``).

The result mirrors the subset of ezc3d's dictionary that :func:`formats.c3d.read_c3d` uses:
``{"header": {"points": {...}}, "parameters": {GROUP: {NAME: {"value": ...}}},
"data": {"points": (4, N, F), "meta_points": {"residuals": (1, N, F),
"camera_masks": (7, N, F)}}}``; numeric values are arrays shaped like the parameter's dimensions (column-major), char values
lists of str.
Invalid points are NaN with residual -1, as in ezc3d.
"""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from formats.errors import InputError

PROCESSORS = {84: "Intel", 85: "DEC", 86: "SGI/MIPS"}


def processor_type(path: str | Path) -> int:
    """The processor type byte (84 Intel, 85 DEC, 86 SGI/MIPS) of a C3D file."""
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(2)
        if len(head) < 2 or head[1] != 0x50:
            raise InputError(path, "<header>", "corrupt or not a C3D file (no 0x50 key byte)")
        fh.seek(max(head[0] - 1, 0) * 512)
        phead = fh.read(4)
    if len(phead) < 4:
        raise InputError(path, "<parameters>", "truncated: no parameter section header")
    return phead[3]


def dec_to_ieee(raw: bytes) -> np.ndarray:
    """VAX F-floating (DEC) float32s -> float64. A DEC float is two little-endian 16-bit words,
    the high word first, with exponent bias 128 and the hidden bit at 0.5: swapping the words
    gives the IEEE bit pattern of 4x the value."""
    b = np.frombuffer(raw, np.uint8).reshape(-1, 4)[:, [2, 3, 0, 1]]
    return np.ascontiguousarray(b).view("<f4").ravel().astype(np.float64) / 4.0


class _Reader:
    def __init__(self, path: Path, proc: int):
        self.path, self.proc = path, proc
        self.e = ">" if proc == 86 else "<"

    def floats(self, raw: bytes) -> np.ndarray:
        if self.proc == 85:
            return dec_to_ieee(raw)
        return np.frombuffer(raw, self.e + "f4").astype(np.float64)

    def ints(self, raw: bytes) -> np.ndarray:
        return np.frombuffer(raw, self.e + "i2").astype(np.int64)


def _parameters(path: Path, sec: bytes, rd: _Reader) -> dict:
    """Parse the parameter section ``sec`` (starting with its 4-byte header)."""
    groups: dict[int, str] = {}
    params: list[tuple[int, str, object]] = []
    pos, n = 4, len(sec)
    while pos + 2 <= n:
        name_len = abs(struct.unpack("b", sec[pos:pos + 1])[0])
        gid = struct.unpack("b", sec[pos + 1:pos + 2])[0]
        if name_len == 0:
            break
        p = pos + 2 + name_len
        if p + 2 > n:
            raise InputError(path, "<parameters>", f"corrupt: record at byte {pos} past the end "
                             f"({PROCESSORS[rd.proc]} file)")
        name = sec[pos + 2:p].decode("latin-1").strip().upper()
        nxt = struct.unpack(rd.e + "h", sec[p:p + 2])[0]
        q = p + 2
        if gid < 0:
            groups[-gid] = name
        elif gid > 0:
            if q + 2 > n:
                raise InputError(path, f"<parameters>:{name}", "corrupt: record past the end")
            typ, ndim = struct.unpack("bB", sec[q:q + 2])
            dims = list(sec[q + 2:q + 2 + ndim])
            count = int(np.prod(dims, dtype=np.int64)) if ndim else 1
            q += 2 + ndim
            nbytes = abs(typ) * count
            if typ not in (-1, 1, 2, 4) or q + nbytes > n:
                raise InputError(path, f"<parameters>:{name}", f"corrupt: type {typ}, "
                                 f"{nbytes} bytes at byte {q} of {n} ({PROCESSORS[rd.proc]} file)")
            raw = sec[q:q + nbytes]
            if typ == -1:  # char: dims[0] is the string length
                text = raw.decode("latin-1")
                if ndim <= 1:
                    value: object = [text.rstrip()]
                else:
                    w = dims[0]
                    value = [text[i:i + w].rstrip() for i in range(0, len(text), w)] if w else []
            elif typ == 1:
                value = np.frombuffer(raw, np.int8).astype(np.int64)
            elif typ == 2:
                value = rd.ints(raw)
            else:
                value = rd.floats(raw)
            if typ != -1 and ndim > 1:  # column-major, like ezc3d
                value = np.reshape(value, dims, order="F")
            params.append((gid, name, value))
        if nxt == 0 or p + nxt + 2 > n:
            # 0 ends the chain; a link leaving the section follows the last record (the SGI
            # files of the C3D sample suite store that last link byte-swapped)
            break
        if nxt < 0 or p + nxt <= pos:
            raise InputError(path, "<parameters>", f"corrupt: record at byte {pos} links "
                             f"backwards ({PROCESSORS[rd.proc]} file)")
        pos = p + nxt
    out: dict[str, dict] = {g: {} for g in groups.values()}
    for gid, name, value in params:
        out.setdefault(groups.get(gid, f"GROUP{gid}"), {})[name] = {"value": value}
    return out


def read_c3d_dict(path: str | Path) -> dict:
    """Parse a C3D file of any processor type (84 Intel, 85 DEC, 86 SGI/MIPS) into the subset
    of ezc3d's dictionary described in the module docstring. Raises InputError naming the file,
    the section and the processor type for what cannot be read."""
    path = Path(path)
    data = path.read_bytes()
    if len(data) < 512 or data[1] != 0x50:
        raise InputError(path, "<header>", "corrupt or not a C3D file (no 0x50 key byte)")
    pblock = data[0]
    psec = data[(pblock - 1) * 512:] if pblock >= 1 else b""
    if len(psec) < 4:
        raise InputError(path, "<parameters>", "truncated: no parameter section")
    proc = psec[3]
    if proc not in PROCESSORS:
        raise InputError(path, "<parameters>", f"unknown processor type {proc} (expected 84 "
                         "Intel, 85 DEC or 86 SGI/MIPS)")
    rd = _Reader(path, proc)
    psec = psec[:max(psec[2], 1) * 512]
    params = _parameters(path, psec, rd)

    w = rd.ints(data[2:20])  # words 2..10 (int16)
    n_pts, n_analog, first, last = (int(v) & 0xFFFF for v in w[:4])
    data_start = int(w[7]) & 0xFFFF
    h_scale = float(rd.floats(data[12:16])[0])
    h_rate = float(rd.floats(data[20:24])[0])

    def p(group, name):
        v = params.get(group, {}).get(name)
        return None if v is None else v["value"]

    scale_v = p("POINT", "SCALE")
    scale = float(scale_v[0]) if scale_v is not None and len(scale_v) else h_scale
    ds = p("POINT", "DATA_START")
    if ds is not None and len(ds):
        data_start = int(ds[0]) & 0xFFFF
    n_frames = last - first + 1 if last >= first else 0
    s, e = p("TRIAL", "ACTUAL_START_FIELD"), p("TRIAL", "ACTUAL_END_FIELD")
    if s is not None and e is not None and len(s) >= 2 and len(e) >= 2:
        s0 = (int(s[0]) & 0xFFFF) + 65536 * (int(s[1]) & 0xFFFF)
        e0 = (int(e[0]) & 0xFFFF) + 65536 * (int(e[1]) & 0xFFFF)
        n_frames = e0 - s0 + 1

    is_float = scale < 0
    word = 4 if is_float else 2
    per_frame = 4 * n_pts + n_analog
    off = (data_start - 1) * 512
    if data_start < 1 or (per_frame and off < (pblock - 1) * 512 + len(psec)):
        raise InputError(path, "POINT:DATA_START", f"data start block {data_start} is inside the "
                         f"header or parameters ({PROCESSORS[proc]} file)")
    need = n_frames * per_frame * word
    have = len(data) - off
    if per_frame and have < need:
        got = max(have, 0) // (per_frame * word)
        raise InputError(path, "<data>", f"truncated: {got} of {n_frames} frames present "
                         f"({PROCESSORS[proc]} file)", frame=got)
    raw = data[off:off + need]
    words = (rd.floats(raw) if is_float else rd.ints(raw).astype(np.float64))
    words = words.reshape(n_frames, per_frame) if per_frame else np.zeros((n_frames, 0))
    pt = words[:, :4 * n_pts].reshape(n_frames, n_pts, 4)
    xyz = pt[..., :3] * (1.0 if is_float else scale)
    invalid = ~(pt[..., 3] >= 0)  # negative (or, in float data, NaN): no point
    fourth = np.round(np.where(invalid, 0.0, pt[..., 3])).astype(np.int64)
    residual = np.where(invalid, -1.0, ((fourth >> 8) & 0xFF) * abs(scale))
    masks = np.stack([(fourth >> b) & 1 for b in range(7)]).astype(bool) & ~invalid
    xyz = np.where(invalid[..., None], np.nan, xyz)
    points = np.ones((4, n_pts, n_frames))
    points[:3] = xyz.transpose(2, 1, 0)
    return {
        "processor": proc,
        "header": {"points": {"size": n_pts, "frame_rate": h_rate, "first_frame": first - 1,
                              "last_frame": first - 1 + n_frames - 1},
                   "analogs": {"size": n_analog}},  # analog samples are not read
        "parameters": params,
        "data": {"points": points,
                 "meta_points": {"residuals": residual.T[None],
                                 "camera_masks": masks.transpose(0, 2, 1)}},
    }
