"""Damaged device files, fuzzed: the shared files truncated, with bytes overwritten or a
stretch replaced by random bytes, each read in a child process with its address space and CPU
time bounded. Each gives a recording whose times strictly increase, or one DeviceFileError
line; never a traceback, an abort of the native reader, or a hang."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

DEVICES = Path(__file__).resolve().parents[2] / "shared" / "data" / "devices"
NAMES = sorted(p.name for p in DEVICES.iterdir() if p.suffix in (".cwa", ".bin", ".gt3x"))
#: address space of the child: actfast reserves (not touches) about 3.2 GB for a .gt3x's
#: samples whatever its size, so the bound is above that and far below what a header count
#: taken at its word would reserve
ADDRESS_SPACE_BYTES = 8 << 30
CPU_S = 60

CHILD = f"""
import resource, sys
resource.setrlimit(resource.RLIMIT_AS, ({ADDRESS_SPACE_BYTES}, {ADDRESS_SPACE_BYTES}))
resource.setrlimit(resource.RLIMIT_CPU, ({CPU_S}, {CPU_S}))
import numpy as np
from recal.errors import DeviceFileError
from recal.io.device_files import open_device
try:
    rec = open_device(sys.argv[1])
except DeviceFileError as e:
    assert "\\n" not in str(e)
    print("error", e)
    sys.exit(0)
last = None
for b in rec.batches(4096):
    assert (np.diff(b.t_us) > 0).all() and (last is None or b.t_us[0] > last)
    assert b.v.shape == (len(b), 3) and b.aux.shape == (len(b), len(rec.aux_names))
    last = b.t_us[-1]
print("ok", len(rec))
"""

mutation = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0, 1)),
    st.tuples(st.just("overwrite"), st.lists(st.tuples(st.floats(0, 1), st.integers(0, 255)),
                                             min_size=1, max_size=40)),
    st.tuples(st.just("splice"), st.floats(0, 1), st.binary(min_size=0, max_size=3000),
              st.integers(0, 3000)),
)


def _mutate(data: bytes, m: tuple) -> bytes:
    out = bytearray(data)
    if m[0] == "truncate":
        return bytes(out[:int(m[1] * len(out))])
    if m[0] == "overwrite":
        for where, value in m[1]:
            out[min(len(out) - 1, int(where * len(out)))] = value
        return bytes(out)
    at = int(m[1] * len(out))
    out[at:at + m[3]] = m[2]
    return bytes(out)


@pytest.mark.slow
@settings(max_examples=15, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=st.sampled_from(NAMES), m=mutation)
def test_a_damaged_file_gives_a_recording_or_one_error(tmp_path: Path, name: str,
                                                       m: tuple) -> None:
    path = tmp_path / "fuzzed"
    path.write_bytes(_mutate((DEVICES / name).read_bytes(), m))
    done = subprocess.run([sys.executable, "-c", CHILD, str(path)], capture_output=True,
                          text=True, timeout=2 * CPU_S)
    assert done.returncode == 0, (name, m[0], done.returncode, done.stderr[-2000:])
    assert done.stdout.startswith(("ok", "error")), done.stdout
