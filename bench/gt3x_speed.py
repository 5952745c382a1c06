"""Reading speed of recal's .gt3x decoder (`recal.io.gt3x`) beside actfast and, where it is
installed in a throwaway environment of its own, pygt3x (GPL-3.0: run as a separate program,
never imported by recal).

Files: the public ACTIVITY file (../shared/data/devices/actfast_actigraph.gt3x, 81 s at 60 Hz,
read many times), and synthetic files of ``--hours`` written here with numpy (one record a
second, 30 Hz, a slow random walk quantized to the file's counts): one of ACTIVITY records
(12-bit, actfast reads it too) and one of ACTIVITY2 records (the Link's layout: recal and
pygt3x only). Each reader reads each file ``--repeats`` times; the best wall time counts
(samples / s). pygt3x is timed inside its own process, from opening the file to its data
frame, so that its start-up is not counted. Samples are as each reader returns them (a reader
that fills idle sleep is not credited with its fill: these files have none); the counts are
printed so that a reader that returned less is seen, and the largest difference of its values
from recal's.

    python bench/gt3x_speed.py [--hours 24] [--repeats 3] [--pygt3x /tmp/pyg/bin/python]
                               [--also FILE.gt3x ...]
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from recal.io.gt3x import read_gt3x

DEVICES = Path(__file__).resolve().parents[2] / "shared" / "data" / "devices"
DOTNET_TICKS_AT_UNIX_EPOCH = 621_355_968_000_000_000
START_S = 1_700_000_000
PYGT3X_SCRIPT = """
import sys, time
import numpy as np
from pygt3x.reader import FileReader
t0 = time.perf_counter()
with FileReader(sys.argv[1]) as reader:
    df = reader.to_pandas()
seconds = time.perf_counter() - t0
awake = ~df["IdleSleepMode"].to_numpy(bool) if "IdleSleepMode" in df else slice(None)
np.save(sys.argv[2], df[["X", "Y", "Z"]].to_numpy()[awake])   # its idle-sleep fill left out
print(len(df), seconds)
"""


def _records(kind: int, payload: np.ndarray) -> bytes:
    """(S, P) payload bytes -> S log records, one a second, with their checksums."""
    s, p = payload.shape
    head = np.zeros((s, 8), np.uint8)
    head[:, 0], head[:, 1] = 0x1E, kind
    head[:, 2:6] = (START_S + np.arange(s, dtype=np.uint32)).astype("<u4").view(np.uint8
                                                                                 ).reshape(s, 4)
    head[:, 6:8] = np.frombuffer(np.uint16(p).astype("<u2").tobytes(), np.uint8)
    body = np.concatenate([head, payload], axis=1)
    check = ~np.bitwise_xor.reduce(body, axis=1)
    return np.concatenate([body, check[:, None]], axis=1).tobytes()


def _counts(seconds: int, rate: int, lim: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(0, 2, size=(seconds * rate, 3)), axis=0)
    return np.clip(np.rint(walk % 400 + np.array([0, 0, 256])), -lim, lim).astype(np.int64)


def _pack12(c: np.ndarray, rate: int) -> np.ndarray:
    """Counts -> (S, rate*36/8) bytes, YXZ, 12-bit big-endian nibbles (rate even)."""
    u = (c[:, [1, 0, 2]] & 0xFFF).reshape(-1)
    nib = np.stack([u >> 8, (u >> 4) & 0xF, u & 0xF], axis=1).reshape(-1)
    return ((nib[0::2] << 4) | nib[1::2]).astype(np.uint8).reshape(-1, rate * 36 // 8)


def write_synthetic(path: Path, hours: float, kind: int, rate: int = 30) -> int:
    seconds = int(hours * 3600)
    if kind == 0x00:
        c = _counts(seconds, rate, 2046)
        payload = _pack12(c, rate)
    else:
        c = _counts(seconds, rate, 32767)
        payload = c.astype("<i2").view(np.uint8).reshape(seconds, rate * 6)
    info = (f"Serial Number: MOS2E00000000\nDevice Type: wGT3XBT\nFirmware: 1.9.2\n"
            f"Sample Rate: {rate}\nStart Date: {DOTNET_TICKS_AT_UNIX_EPOCH + START_S * 10**7}\n"
            f"Stop Date: 0\nLast Sample Time: "
            f"{DOTNET_TICKS_AT_UNIX_EPOCH + (START_S + seconds) * 10**7}\n"
            "TimeZone: 00:00:00\nAcceleration Scale: 256.0\nAcceleration Min: -8.0\n"
            "Acceleration Max: 8.0\n")
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("info.txt", info)
        # PARAMETERS with ACCEL_SCALE 256 (Parameters.md's float 0x09400000) and the rate, as
        # devices write it first (actfast 1.3 scales wrongly without it)
        params = np.array([[0, 55, 0x0000, 0x0940], [1, 10, rate, 0]], "<u2").view(np.uint8)
        z.writestr("log.bin", _records(0x15, params.reshape(1, -1)) + _records(kind, payload))
    return len(c)


Result = tuple[float, np.ndarray]    # best seconds per read, the (N, 3) values in g


def _best(fn: Callable[[Path], np.ndarray], path: Path, inner: int, repeats: int) -> Result:
    """Best of ``repeats`` of the mean time of ``inner`` reads; the values read."""
    best, v = float("inf"), np.zeros((0, 3))
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            v = fn(path)
        best = min(best, (time.perf_counter() - t0) / inner)
    return best, v


def _tried(fn: Callable[[Path], np.ndarray], path: Path, inner: int,
           repeats: int) -> Result | None:
    try:
        return _best(fn, path, inner, repeats)
    except Exception as exc:  # a reader that refuses a file: said, and the others still run
        print(f"    {fn.__name__.strip('_')} failed on {path.name}: {str(exc)[:120]}")
        return None


def _recal(path: Path) -> np.ndarray:
    return read_gt3x(path).acc_g


def _actfast(path: Path) -> np.ndarray:
    import actfast

    return np.asarray(actfast.read(str(path))["timeseries"]["acceleration"]["acceleration"])


def _pygt3x(python: str, path: Path, repeats: int) -> Result | None:
    best = float("inf")
    with tempfile.TemporaryDirectory() as tmp:  # never beside the input (read-only data)
        out = Path(tmp) / "pygt3x.npy"
        for _ in range(repeats):
            r = subprocess.run([python, "-c", PYGT3X_SCRIPT, str(path), str(out)],
                               capture_output=True, text=True, timeout=600)
            if r.returncode != 0:
                print(f"    pygt3x failed: {r.stderr.strip().splitlines()[-1:]}")
                return None
            best = min(best, float(r.stdout.split()[1]))
        return best, np.load(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--hours", type=float, default=24.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--pygt3x", default="/tmp/pyg/bin/python",
                    help="a Python that has pygt3x (skipped if absent)")
    ap.add_argument("--also", nargs="*", default=[], type=Path,
                    help="more .gt3x files to read with each reader (e.g. pygt3x's test data)")
    a = ap.parse_args(argv)
    has_pyg = Path(a.pygt3x).exists()
    with tempfile.TemporaryDirectory() as tmp:
        files = [("public ACTIVITY 81 s x20", DEVICES / "actfast_actigraph.gt3x", 20)]
        for kind, name in ((0x00, "ACTIVITY"), (0x1A, "ACTIVITY2")):
            p = Path(tmp) / f"{name}.gt3x"
            n = write_synthetic(p, a.hours, kind)
            files.append((f"synthetic {name} {a.hours:g} h ({n} samples)", p, 1))
        files += [(p.name, p, 1) for p in a.also]
        print(f"{'file':44s} {'reader':8s} {'samples':>10s} {'s':>8s} {'samples/s':>12s} "
              "max|diff| to recal (g)")
        for label, path, inner in files:
            readers: list[tuple[str, Result | None]] = [
                ("recal", _tried(_recal, path, inner, a.repeats))]
            if "ACTIVITY2" not in label:
                readers.append(("actfast", _tried(_actfast, path, inner, a.repeats)))
            if has_pyg:
                readers.append(("pygt3x", _pygt3x(a.pygt3x, path, a.repeats)))
            ours = readers[0][1][1] if readers[0][1] is not None else np.zeros((0, 3))
            for name, res in readers:
                if res is not None:
                    sec, v = res
                    diff = (f"{np.abs(v - ours).max():.2g}" if v.shape == ours.shape
                            else "different counts")
                    print(f"{label:44s} {name:8s} {len(v):10d} {sec:8.3f} {len(v) / sec:12.3g} "
                          f"{diff}")
        if not has_pyg:
            print(f"pygt3x not measured: no {a.pygt3x} (install it in a throwaway venv)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
