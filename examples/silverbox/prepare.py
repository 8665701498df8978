"""Silverbox (Wigren & Schoukens 2013) segments for the example spec, from
``../shared/data/silverbox/silverbox.npz`` (see its README).

    python -m examples.silverbox.prepare

The multisine part of the ``SNLS80mV`` record holds 10 realisations of an odd random-phase
multisine, each preceded by a short zero-input gap (the circuit is then at rest, which is
where our simulators start). ``START`` lists where each realisation's input begins (found
as the end of the gap: 50-sample moving RMS of the input above 3 mV). A segment is
``LENGTH`` samples from ``LEAD`` samples before a start.

- offsets: the input and output offsets measured on the zero-input tail of the record
  (samples 127,500 on) are subtracted (the archive README suggests removing them);
- the input is **advanced by half a sample** (FFT, zero-padded), as for the Bouc-Wen example:
  our simulators hold ``u[i]`` over a sample, which lags the circuit's continuous input by
  dt/2 (20 degrees at the 69 Hz resonance). Least-squares check on the fit window (scipy,
  not ABC): linear NMSE 8.85 -> 2.57 and cubic 6.45 -> 0.034 with the advance.

Writes ``force.npy``, ``displacement.npy`` (realisation 1: fit [0, 1500), test [1500,
3000) in the spec); :func:`segments` gives the held-out realisations 2..9 the same way
(8 and 9 lie in the benchmark's official test range [105712, 127400)).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SOURCE = HERE.parents[2] / "shared" / "data" / "silverbox" / "silverbox.npz"
START = (40563, 49255, 57949, 66641, 75331, 84022, 92717, 101406, 110101, 118791)
LEAD, LENGTH, FIT = 30, 3000, 1
TAIL = 127_500


def advance(x: np.ndarray, samples: float, pad: int = 8192) -> np.ndarray:
    n = x.size + pad
    spectrum = np.fft.rfft(np.concatenate([x, np.zeros(pad)]))
    return np.fft.irfft(spectrum * np.exp(2j * np.pi * np.fft.rfftfreq(n) * samples), n)[: x.size]


def segments(source: Path = SOURCE) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """{realisation: (input, output)} of every multisine realisation, offsets removed."""
    with np.load(source) as z:
        u, y = z["SNLS80mV_V1"], z["SNLS80mV_V2"]
    u = advance(u - u[TAIL:].mean(), 0.5)
    y = y - y[TAIL:].mean()
    return {r: (u[s - LEAD : s - LEAD + LENGTH], y[s - LEAD : s - LEAD + LENGTH]) for r, s in enumerate(START)}


def main() -> None:
    seg = segments()
    np.save(HERE / "force.npy", seg[FIT][0])
    np.save(HERE / "displacement.npy", seg[FIT][1])
    print(f"wrote {HERE}/force.npy, displacement.npy")


if __name__ == "__main__":
    main()
