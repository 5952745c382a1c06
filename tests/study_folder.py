"""A study's folder for the tests and the bench: device files of two formats (synthetic, from
`device_writers`), recal's own MCAP and CSV recordings, and the files a real study folder also
holds: one corrupt (a device file's header and then noise), one unreadable (a link to a file
no longer there), one cut short (a .cwa whose
last third is gone), one too short, one with no still period (a wearer never at rest), a text
file, a picture and a named pipe (skipped: not recordings)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from device_writers import DeviceRun, device_signal, write_cwa, write_geneactiv_bin
from recal.cli import main
from recal.sim.sensor import SensorSpec

__all__ = ["EXPECTED", "counts", "make_folder", "write_device_files"]

RATE_HZ = 25


def sensor(seed: int) -> SensorSpec:
    """A worn device's sensor: offsets of tens of mg and gains off by about 1 %, as a study's
    devices have (the calibration has something to do)."""
    rng = np.random.default_rng(seed)
    return SensorSpec(counts_per_g=256.0, full_scale_g=8.0,
                      offset_g=tuple(rng.uniform(-0.05, 0.05, 3)),
                      gain=tuple(rng.uniform(-0.02, 0.02, 3)))


#: each file of `make_folder`: its status and, where it failed, the failure word
EXPECTED: dict[str, tuple[str, str | None]] = {
    "wearer1/day.cwa": ("ok", None),
    "wearer1/cut.cwa": ("ok", None),  # cut short: the rest is read and calibrated
    "wearer2/day.bin": ("ok", None),
    "lab/sim.mcap": ("ok", None),
    "lab/sim.csv": ("ok", None),
    "wearer3/junk.cwa": ("failed", "corrupt"),
    "wearer3/gone.cwa": ("failed", "unreadable"),  # a link to a file no longer there
    "wearer3/short.cwa": ("failed", "too short"),
    "wearer3/moving.cwa": ("failed", "no still period"),
    "README.txt": ("skipped", None),
    "photo.png": ("skipped", None),
    "wearer3/pipe": ("skipped", None),  # a named pipe: opening it would wait forever
}


def counts() -> dict[str, int]:
    """The rows of `make_folder` by status."""
    statuses = [status for status, _ in EXPECTED.values()]
    return {s: statuses.count(s) for s in ("ok", "failed", "skipped")}


def write_device_files(folder: Path, n: int, hours: float, fmt: str = "cwa",
                       seed: int = 1, rate_hz: int = RATE_HZ) -> list[Path]:
    """n synthetic device files of ``hours`` each (different wearers and sensors)."""
    writer = {"cwa": write_cwa, "bin": write_geneactiv_bin}[fmt]
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(n):
        path = folder / f"wearer{i:03d}.{fmt}"
        writer(path, device_signal(DeviceRun(hours=hours, nominal_hz=rate_hz, real_hz=rate_hz,
                                             seed=seed + i, sensor=sensor(seed + i))))
        out.append(path)
    return out


def make_folder(root: Path, hours: float = 0.1) -> Path:
    """The mixed folder of `EXPECTED` under root (module doc); minutes of data per file."""
    (root / "wearer1").mkdir(parents=True)
    (root / "wearer2").mkdir()
    (root / "wearer3").mkdir()
    (root / "lab").mkdir()
    day = device_signal(DeviceRun(hours=hours, nominal_hz=RATE_HZ, real_hz=RATE_HZ, seed=1,
                                  sensor=sensor(1)))
    write_cwa(root / "wearer1/day.cwa", day)
    whole = (root / "wearer1/day.cwa").read_bytes()
    (root / "wearer1/cut.cwa").write_bytes(whole[:2 * len(whole) // 3 + 100])
    write_geneactiv_bin(root / "wearer2/day.bin", device_signal(
        DeviceRun(hours=hours, nominal_hz=RATE_HZ, real_hz=RATE_HZ, seed=2, sensor=sensor(2))))
    rng = np.random.default_rng(3)
    (root / "wearer3/junk.cwa").write_bytes(whole[:1024] + rng.bytes(4096))
    (root / "wearer3/gone.cwa").symlink_to(root / "wearer3/moved-away.cwa")
    write_cwa(root / "wearer3/short.cwa", device_signal(
        DeviceRun(hours=0.005, nominal_hz=RATE_HZ, real_hz=RATE_HZ, seed=4)))
    moving = device_signal(DeviceRun(hours=hours, nominal_hz=RATE_HZ, real_hz=RATE_HZ, seed=5))
    shaken = moving.counts + np.round(rng.normal(0, 0.4 * 256, moving.counts.shape))
    write_cwa(root / "wearer3/moving.cwa",
              dataclasses.replace(moving, counts=shaken.astype(np.int64)))
    for name in ("sim.mcap", "sim.csv"):
        assert main(["simulate", "--out", str(root / "lab" / name), "--hours", str(hours),
                     "--seed", "7"]) == 0
        (root / "lab" / name).with_suffix(".truth.npz").unlink()
    os.mkfifo(root / "wearer3/pipe")
    (root / "README.txt").write_text("wearers 1-3, collected in March\n")
    (root / "photo.png").write_bytes(b"\x89PNG\r\n\x1a\n" + rng.bytes(256))
    return root
