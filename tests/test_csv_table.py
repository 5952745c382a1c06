"""CSV import/export: exact round trips, accepted layouts, bad rows, clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from recal.errors import InputError, UsageError
from recal.io.csv_table import CsvTable, read_csv, write_calibrated_csv, write_raw_csv
from recal.samples import CalibratedBatch, RawBatch


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def _awkward_floats(n: int, seed: int = 0) -> np.ndarray:
    """Values whose text form is easy to get wrong: tiny, huge, negative zero, 0.1-style."""
    rng = np.random.default_rng(seed)
    values = rng.normal(size=n) * 10.0 ** rng.integers(-300, 300, size=n)
    values[:8] = [0.1, -0.0, 5e-324, 1.7976931348623157e308, 1 / 3, np.nan, np.inf, -np.inf]
    return values


def test_raw_round_trip_is_exact(tmp_path: Path) -> None:
    n = 500
    t_us = 1_700_000_000_000_000 + np.arange(n, dtype=np.int64) * 997
    v = np.column_stack([_awkward_floats(n, s) for s in range(3)])
    batch = RawBatch(t_us, v, np.column_stack([_awkward_floats(n, 9), np.arange(n)]),
                     ("Temp °C", "vdd"))
    path = tmp_path / "raw.csv"
    write_raw_csv(path, batch)
    assert path.read_text().splitlines()[0] == "t_us,x,y,z,Temp °C,vdd"
    table = read_csv(path)
    assert isinstance(table, CsvTable)
    assert (table.units, table.time_column, table.skipped_rows) == ("counts", "t_us", 0)
    assert np.array_equal(table.batch.t_us, t_us)
    assert np.array_equal(table.batch.v, v, equal_nan=True)
    assert np.array_equal(np.signbit(table.batch.v), np.signbit(v))
    assert np.array_equal(table.batch.aux, batch.aux, equal_nan=True)
    assert table.batch.aux_names == ("Temp °C", "vdd")


def test_raw_with_units_writes_suffixed_axes_that_read_back_with_the_unit(tmp_path: Path) -> None:
    batch = RawBatch([0, 10], [[0.0, 0.0, 9.80665], [0.1, 0.2, 9.7]], np.zeros((2, 0)))
    path = tmp_path / "ms2.csv"
    write_raw_csv(path, batch, units="ms2")
    assert path.read_text().splitlines()[0] == "t_us,x_ms2,y_ms2,z_ms2"
    table = read_csv(path)
    assert table.units == "ms2"
    assert np.array_equal(table.batch.v, batch.v)  # values are kept, not converted


def test_calibrated_export_reads_back_in_g_with_detector_channels(tmp_path: Path) -> None:
    n = 100
    rng = np.random.default_rng(3)
    batch = CalibratedBatch(np.arange(n) * 10_000, rng.normal(size=(n, 3)), rng.random(n) > 0.3,
                            rng.random(n))
    plain, full = tmp_path / "cal.csv", tmp_path / "cal-full.csv"
    write_calibrated_csv(plain, batch)
    write_calibrated_csv(full, batch, with_detector=True)
    assert plain.read_text().splitlines()[0] == "t_us,x_g,y_g,z_g"
    table = read_csv(full)
    assert table.units == "g"
    assert np.array_equal(table.batch.v, batch.a_g)
    assert np.array_equal(table.batch.channel("quasi_static"), batch.quasi_static)
    assert np.array_equal(table.batch.channel("detector_g"), batch.detector_g)
    assert len(read_csv(plain).batch.aux_names) == 0


@pytest.mark.parametrize("column, values, expected_us", [
    ("t_s", ["1700000000.123456", "1700000000.123457"], [1_700_000_000_123_456,
                                                         1_700_000_000_123_457]),
    ("t_ms", ["0.5", "1.001"], [500, 1001]),
    ("T_US", ["-5", "7"], [-5, 7]),
])
def test_time_columns_are_converted_to_microseconds(tmp_path: Path, column: str,
                                                    values: list[str],
                                                    expected_us: list[int]) -> None:
    rows = "".join(f"{t},1,2,3\n" for t in values)
    table = read_csv(_write(tmp_path / "t.csv", f"{column},x,y,z\n{rows}"))
    assert table.batch.t_us.tolist() == expected_us
    assert table.time_column == column.lower()


def test_without_a_time_column_times_are_synthesized_from_the_rate(tmp_path: Path) -> None:
    path = _write(tmp_path / "no-time.csv", "x,y,z\n1,2,3\n4,5,6\n7,8,9\n")
    with pytest.raises(InputError, match="--rate"):
        read_csv(path)
    table = read_csv(path, rate_hz=3.0, t0_us=1000)
    assert table.batch.t_us.tolist() == [1000, 334_333, 667_667]
    assert table.time_column == "synthesized"


def test_several_time_columns_keep_the_others_as_auxiliary(tmp_path: Path) -> None:
    path = _write(tmp_path / "two-times.csv", "t_s,t_us,x,y,z\n0.5,7,1,2,3\n")
    table = read_csv(path)
    assert table.batch.t_us.tolist() == [7] and table.batch.aux_names == ("t_s",)


def test_units_come_from_the_header_and_must_agree(tmp_path: Path) -> None:
    path = _write(tmp_path / "g.csv", "t_us,x_g,y_g,z_g,x\n0,0,0,1,5\n")
    table = read_csv(path, units="g")
    assert table.units == "g" and table.batch.aux_names == ("x",)
    with pytest.raises(InputError, match="header says 'g'"):
        read_csv(path, units="counts")
    with pytest.raises(UsageError, match="units must be one of"):
        read_csv(path, units="mg")  # type: ignore[arg-type]
    plain = _write(tmp_path / "plain.csv", "t_us,x,y,z\n0,1,2,3\n")
    assert read_csv(plain).units == "counts" and read_csv(plain, units="ms2").units == "ms2"


def test_bad_rows_are_skipped_and_counted_with_line_numbers(tmp_path: Path) -> None:
    text = ("# exported by a logger\n"  # line 1
            "t_us,x,y,z,temp\n"  # 2
            "0,1,2,3,20\n"  # 3
            "\n"  # 4: blank, ignored
            "1000,1,2\n"  # 5: too few fields
            "2000,1,oops,3,20\n"  # 6: not a number
            "# a comment in the middle\n"  # 7: ignored
            "3000,4,5,6,\n"  # 8: an empty auxiliary field is NaN, kept
            "nan,4,5,6,20\n"  # 9: no time
            ",4,5,6,20\n"  # 10: empty time
            "4000,7,8,9,21\n")  # 11
    table = read_csv(_write(tmp_path / "bad.csv", text))
    assert table.skipped_rows == 4 and table.skipped_lines == (5, 6, 9, 10)
    assert table.batch.t_us.tolist() == [0, 3000, 4000]
    assert np.isnan(table.batch.channel("temp")[1])
    assert table.batch.v[2].tolist() == [7.0, 8.0, 9.0]


def test_quotes_bom_crlf_and_spaces_are_tolerated(tmp_path: Path) -> None:
    path = tmp_path / "excel.csv"
    path.write_bytes('\ufeff"t_us", "X" ,"y","z"," Temp "\r\n0, 1 ,2,3,"4"\r\n5,6,7,8,9\r\n'
                     .encode())
    table = read_csv(path)
    assert table.batch.t_us.tolist() == [0, 5]
    assert table.batch.v.tolist() == [[1, 2, 3], [6, 7, 8]]
    assert table.batch.aux_names == ("Temp",) and table.skipped_rows == 0


@pytest.mark.parametrize("text, reason", [
    ("", "no header"),
    ("# only a comment\n\n", "no header"),
    ("t_us,x,y\n0,1,2\n", "no axis columns"),
    ("t_us,x_g,y_g,z_ms2\n0,1,2,3\n", "no axis columns"),
    ("t_us,x,y,z,X\n0,1,2,3,4\n", "duplicate column"),
    ("t_us,x,y,z,,\n0,1,2,3,4,5\n", "empty column name"),
])
def test_missing_header_or_columns_are_clear_errors(tmp_path: Path, text: str,
                                                    reason: str) -> None:
    with pytest.raises(InputError, match=reason):
        read_csv(_write(tmp_path / "broken.csv", text))


def test_header_only_gives_an_empty_batch(tmp_path: Path) -> None:
    table = read_csv(_write(tmp_path / "empty.csv", "t_us,x,y,z,temp\n"))
    assert len(table.batch) == 0 and table.batch.aux_names == ("temp",)
    write_raw_csv(tmp_path / "out.csv", RawBatch.empty(("a",)))
    assert len(read_csv(tmp_path / "out.csv").batch) == 0


def test_aux_names_that_cannot_round_trip_are_refused(tmp_path: Path) -> None:
    for names in (("x",), ("T_US",), ("a,b",), ('q"',), ("a", "A")):
        batch = RawBatch([0], [[1, 2, 3]], np.zeros((1, len(names))), names)
        with pytest.raises(InputError):
            write_raw_csv(tmp_path / "bad.csv", batch)


def test_a_large_table_round_trips(tmp_path: Path) -> None:
    n = 200_000  # more than one write chunk
    rng = np.random.default_rng(5)
    batch = RawBatch(np.arange(n) * 1000, np.round(rng.normal(size=(n, 3)) * 512),
                     rng.normal(size=(n, 1)), ("temp",))
    path = tmp_path / "big.csv"
    write_raw_csv(path, batch)
    table = read_csv(path)
    assert np.array_equal(table.batch.v, batch.v) and np.array_equal(table.batch.aux, batch.aux)
    assert np.array_equal(table.batch.t_us, batch.t_us)


def test_cli_import_then_raw_export_keeps_the_unit(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """`recal import` of a table in g, `recal export --topic raw` of it: the axes come back as
    x_g, y_g, z_g (from the recording's metadata), so importing the export again still reads g,
    not counts; a recording without a unit (a live log) exports plain x, y, z."""
    from recal import cli
    from recal.io import recording
    from recal.io.recording_writer import RecordingWriter

    src = tmp_path / "in.csv"
    src.write_text("t_us,x_g,y_g,z_g\n0,0.5,0.25,1.0\n10000,0.5,0.25,1.0\n")
    assert cli.main(["import", str(src), "--out", str(tmp_path / "a.mcap")]) == 0
    assert recording.metadata(tmp_path / "a.mcap")["units"] == "g"
    again = ["import", str(src), "--out", str(tmp_path / "a.mcap")]
    assert cli.main(again) == 2 and cli.main([*again, "--overwrite"]) == 0  # only when asked
    assert cli.main(["export", str(tmp_path / "a.mcap"), "--csv", str(tmp_path / "a.csv"),
                     "--topic", "raw"]) == 0
    assert (tmp_path / "a.csv").read_text().splitlines()[0] == "t_us,x_g,y_g,z_g"
    back = read_csv(tmp_path / "a.csv")
    assert back.units == "g" and np.array_equal(back.batch.v, [[0.5, 0.25, 1.0]] * 2)
    with RecordingWriter(tmp_path / "live.mcap", fsync=False) as w:
        w.write_raw("s1", back.batch, 1)
    assert recording.metadata(tmp_path / "live.mcap").get("units") is None
    assert cli.main(["export", str(tmp_path / "live.mcap"), "--csv", str(tmp_path / "b.csv"),
                     "--topic", "raw"]) == 0
    assert (tmp_path / "b.csv").read_text().splitlines()[0] == "t_us,x,y,z"
    capsys.readouterr()


@pytest.mark.parametrize("chunk_lines", [1, 2, 3, 7, 1000])
def test_reading_in_chunks_gives_what_reading_at_once_does(tmp_path: Path,
                                                           chunk_lines: int) -> None:
    """iter_csv (bounded memory: a week at 100 Hz is 60 M rows) chunk by chunk, joined, is
    read_csv: the same samples, synthesized times, bad-row count and line numbers, with
    comments, blank lines, a byte-order mark and CRLF anywhere, including around chunk ends."""
    from recal.io.csv_table import iter_csv

    lines = ["# made by a logger", "", "x_g,y_g,z_g,temp"]
    rng = np.random.default_rng(3)
    for i in range(40):
        if i % 9 == 4:
            lines.append("1,2")  # wrong column count
        elif i % 11 == 6:
            lines.append("# a comment between rows")
        elif i % 13 == 8:
            lines.append("nan_text,1,2,3")
        else:
            x, y, z, t = rng.normal(size=4).tolist()
            lines.append(f"{x!r},{y!r},{z!r},{t!r}")
    path = tmp_path / "chunks.csv"
    path.write_bytes(b"\xef\xbb\xbf" + "\r\n".join(lines).encode() + b"\r\n")
    whole = read_csv(path, rate_hz=50.0, t0_us=123)
    parts = list(iter_csv(path, rate_hz=50.0, t0_us=123, chunk_lines=chunk_lines))
    joined = RawBatch.concat([p.batch for p in parts])
    np.testing.assert_array_equal(joined.t_us, whole.batch.t_us)
    np.testing.assert_array_equal(joined.v, whole.batch.v)
    np.testing.assert_array_equal(joined.aux, whole.batch.aux)
    assert sum(p.skipped_rows for p in parts) == whole.skipped_rows > 0
    assert tuple(n for p in parts for n in p.skipped_lines) == whole.skipped_lines
    assert whole.skipped_lines[0] == 8  # the first "1,2" (the header is line 3)
    assert len(whole.batch) == 40 - whole.skipped_rows - sum(
        1 for i in range(40) if i % 9 != 4 and i % 11 == 6)


def test_a_non_utf8_byte_is_reported_at_its_place_in_the_file(tmp_path: Path) -> None:
    from recal.io.csv_table import iter_csv

    path = tmp_path / "bytes.csv"
    body = b"t_us,x,y,z\n" + b"".join(b"%d,1,2,3\n" % i for i in range(10))
    path.write_bytes(body + b"\xff,1,2,3\n")
    with pytest.raises(InputError, match=f"not UTF-8 text \\(byte {len(body)}\\)"):
        list(iter_csv(path, chunk_lines=3))


def test_cli_import_streams_chunks_and_leaves_nothing_half_written(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """`recal import` a few lines at a time (as a week-long file would go) logs exactly what
    read_csv reads; a bad time found in a later chunk removes the part already written."""
    from recal import cli
    from recal.io import csv_table, recording

    monkeypatch.setattr(csv_table, "_READ_CHUNK_LINES", 7)
    src = tmp_path / "in.csv"
    rows = [f"{i * 10_000},{i},{-i},{2 * i}" if i % 5 else "bad,row" for i in range(60)]
    src.write_text("t_us,x,y,z\n" + "\n".join(rows) + "\n")
    assert cli.main(["import", str(src), "--out", str(tmp_path / "a.mcap")]) == 0
    want = read_csv(src)
    got = recording.read_all_raw(tmp_path / "a.mcap", "imported")
    np.testing.assert_array_equal(got.t_us, want.batch.t_us)
    np.testing.assert_array_equal(got.v, want.batch.v)
    assert f"{len(want.batch)} samples" in capsys.readouterr().out and want.skipped_rows == 12
    src.write_text("t_us,x,y,z\n" + "\n".join([*rows[1:20], "-5,1,2,3"]) + "\n")  # chunk 3
    assert cli.main(["import", str(src), "--out", str(tmp_path / "b.mcap")]) == 2
    assert "times must be from 0" in capsys.readouterr().err
    assert not (tmp_path / "b.mcap").exists()


def _on_a_terminal(args: list[str], cwd: Path) -> str:
    """`python -m recal ARGS` with stdout and stderr on a real pseudo-terminal: all it wrote."""
    import fcntl
    import os
    import pty
    import struct
    import subprocess
    import sys
    import termios
    import time

    master, slave = pty.openpty()
    # a new pty is 0 x 0 and tqdm draws nothing that narrow: 24 rows, 80 columns
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
    proc = subprocess.Popen([sys.executable, "-m", "recal", *args], cwd=cwd, stdin=slave,
                            stdout=slave, stderr=slave, close_fds=True)
    os.close(slave)
    out = b""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            chunk = os.read(master, 65536)
        except OSError:  # EIO: the child closed its side
            break
        if not chunk:
            break
        out += chunk
    os.close(master)
    assert proc.wait(30) == 0, out
    return out.decode("utf-8", "replace")


def test_cli_import_shows_progress_on_a_terminal_only(tmp_path: Path) -> None:
    """A bar on a terminal (a long import shows it is alive), none with --quiet; in a pipe or
    a log there is none either (the CLI error tests see exactly one stderr line)."""
    src = tmp_path / "in.csv"
    src.write_text("t_us,x,y,z\n" + "".join(f"{i * 10_000},1,2,3\n" for i in range(2000)))
    shown = _on_a_terminal(["import", "in.csv", "--out", "a.mcap"], tmp_path)
    assert "import:" in shown and "imported 2000 samples" in shown, shown
    quiet = _on_a_terminal(["import", "in.csv", "--out", "b.mcap", "--quiet"], tmp_path)
    assert "import:" not in quiet and "imported 2000 samples" in quiet, quiet
