"""Standard normal fields, fast: the ziggurat method compiled with numba on a NumPy bit generator.

``numpy.random.Generator.standard_normal`` costs ~8 ns a sample here (2.5 ms for one VGA float32
field; the IR camera's speckle and read noise are two such fields a frame, ~7 % of a static
frame's CPU). Its own ziggurat calls the bit generator through a function pointer per sample.
:func:`standard_normal` draws the raw 64-bit words of the same Generator in bulk
(``bit_generator.random_raw``, ~0.3 ns a word) and runs the ziggurat of Marsaglia & Tsang (2000,
"The Ziggurat Method for Generating Random Variables", 128 layers) over them in a compiled loop.
The layer index comes from bits 32-38 of a word and the signed value from its low 32 bits, so
index and value are independent (the correlation Doornik 2005 found in the original RNOR, which
took both from one 32-bit word, does not arise). Exact in distribution (the tail by Marsaglia's
1964 method, the wedges by rejection), not the same numbers as ``standard_normal``;
deterministic for a given Generator state (tests: moments, tails, Kolmogorov-Smirnov).
"""
from __future__ import annotations

import math

import numpy as np

from synth.jit import kernel

__all__ = ["standard_normal"]

_R = 3.442619855899          # start of the tail (right edge of the base layer)
_V = 9.91256303526217e-3     # area of every layer


def _tables():
    """(k, w, f) of the 128-layer ziggurat for 31-bit magnitudes (Marsaglia & Tsang 2000)."""
    m1 = 2147483648.0
    k = np.zeros(128, np.float64)  # compared with integers: k is made int64 below
    w = np.zeros(128, np.float64)
    f = np.zeros(128, np.float64)
    dn = tn = _R
    q = _V / math.exp(-0.5 * dn * dn)
    k[0] = (dn / q) * m1
    k[1] = 0.0
    w[0] = q / m1
    w[127] = dn / m1
    f[0] = 1.0
    f[127] = math.exp(-0.5 * dn * dn)
    for i in range(126, 0, -1):
        dn = math.sqrt(-2.0 * math.log(_V / dn + math.exp(-0.5 * dn * dn)))
        k[i + 1] = (dn / tn) * m1
        tn = dn
        f[i] = math.exp(-0.5 * dn * dn)
        w[i] = dn / m1
    return k, w, f


_K, _W, _F = _tables()
_K = _K.astype(np.int64)   # the truncation of Marsaglia & Tsang's uint32 table


def standard_normal(rng: np.random.Generator, shape, dtype=np.float32) -> np.ndarray:
    """An array of ``shape`` independent N(0, 1) samples (``dtype`` float32 or float64) drawn
    with the ziggurat from ``rng``'s bit generator (advances ``rng``; see the module docstring)."""
    out = np.empty(shape, dtype)
    flat = out.reshape(-1)
    n = flat.size
    done = 0
    while done < n:
        need = n - done
        raw = rng.bit_generator.random_raw(need + need // 16 + 64)   # rejections take a few % more words
        done += _ziggurat(raw, flat, done, _K, _W, _F)
    return out


@kernel
def _ziggurat(raw, out, start, k, w, f):
    """Fill ``out[start:]`` from the 64-bit words ``raw``; returns how many samples were
    written (fewer when the words ran out: a sample never straddles two calls)."""
    n = out.shape[0]
    m = raw.shape[0]
    pos = 0
    i = start
    inv_r = 1.0 / 3.442619855899
    while i < n and pos < m:
        word = raw[pos]
        lo = np.int64(word & np.uint64(0xFFFFFFFF))
        hz = lo - ((lo >> 31) << 32)              # the low 32 bits as a signed value
        iz = np.int64(word >> np.uint64(32)) & 127  # the layer, from other bits
        if abs(hz) < k[iz]:                       # inside the layer's rectangle (~99 %)
            out[i] = float(hz) * w[iz]
            i += 1
            pos += 1
            continue
        x = 0.0
        ok = False
        p = pos + 1
        while True:
            x = float(hz) * w[iz]
            if iz == 0:                           # the tail beyond R (Marsaglia 1964)
                while p + 1 < m:
                    u1 = (float(raw[p] >> np.uint64(11)) + 0.5) * 1.1102230246251565e-16
                    u2 = (float(raw[p + 1] >> np.uint64(11)) + 0.5) * 1.1102230246251565e-16
                    p += 2
                    t = -math.log(u1) * inv_r
                    y = -math.log(u2)
                    if y + y >= t * t:
                        x = 3.442619855899 + t if hz > 0 else -3.442619855899 - t
                        ok = True
                        break
                break                             # accepted, or out of words
            if p >= m:
                break
            u = (float(raw[p] >> np.uint64(11)) + 0.5) * 1.1102230246251565e-16
            p += 1
            if f[iz] + u * (f[iz - 1] - f[iz]) < math.exp(-0.5 * x * x):
                ok = True                         # under the density in the layer's wedge
                break
            if p >= m:
                break
            word = raw[p]                         # rejected: a new value and layer
            p += 1
            lo = np.int64(word & np.uint64(0xFFFFFFFF))
            hz = lo - ((lo >> 31) << 32)
            iz = np.int64(word >> np.uint64(32)) & 127
            if abs(hz) < k[iz]:
                x = float(hz) * w[iz]
                ok = True
                break
        if not ok:
            break                                 # out of words: the caller draws more
        out[i] = x
        i += 1
        pos = p
    return i - start
