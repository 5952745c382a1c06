"""What a newcomer meets first: messages that name what to type, help that lists what is
accepted, inputs of the wrong kind recognised as such, headline figures that mean what they
seem to. Real files through ``recal.cli.main`` and the real parsers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from recal.cli import main
from recal.io.ascii_lines import AsciiLineParser
from recal.io.csv_table import TIME_COLUMNS


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


# --------------------------------------------------------------------------- import


def test_import_without_a_time_column_names_the_flag(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "xyz.csv"
    src.write_text("x,y,z\n" + "0,0,1024\n" * 20)
    rc, _out, err = _run(["import", str(src), "--out", str(tmp_path / "o.mcap")], capsys)
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert "--rate" in err and "rate_hz" not in err, err
    for name in TIME_COLUMNS:  # and what would have done instead
        assert name in err, err
    rc, out, _ = _run(["import", str(src), "--out", str(tmp_path / "o.mcap"), "--rate", "50"],
                      capsys)
    assert rc == 0 and (tmp_path / "o.mcap").is_file(), out


def test_import_help_lists_every_time_column_accepted(
        capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        main(["import", "--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    for name in TIME_COLUMNS:
        assert name in text, (name, text)
    with pytest.raises(SystemExit):
        main(["--help"])
    summary = capsys.readouterr().out
    line = next(x for x in summary.splitlines() if x.strip().startswith("import"))
    assert all(name in line for name in TIME_COLUMNS), line


@pytest.mark.parametrize("unit, scale", [("t_ms", 1e3), ("t_s", 1e6), ("t_us", 1.0)])
def test_import_reads_each_time_column_it_lists(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], unit: str, scale: float) -> None:
    from recal.io import recording as rec

    src = tmp_path / "in.csv"
    t = np.arange(30) * 20_000 / scale
    src.write_text(f"{unit},x,y,z\n" + "".join(f"{float(v)!r},0,0,1024\n" for v in t))
    rc, _out, err = _run(["import", str(src), "--out", str(tmp_path / "o.mcap")], capsys)
    assert rc == 0, err
    got = np.concatenate([b.t_us for _, b, _ in rec.iter_raw(tmp_path / "o.mcap")])
    np.testing.assert_array_equal(got, np.arange(30) * 20_000)


# --------------------------------------------------------------------------- ascii lines


def test_a_banner_line_is_counted_as_text_not_as_missing_columns() -> None:
    """A device's ``booting...`` line is not a sample that lacks columns (the daemon's hint
    for those, "x,y,z without a time column need the rate", does not apply to it)."""
    parser = AsciiLineParser()
    out = parser.feed(b"booting...\nready, sensor ok\n1000,1,2,3\n2000,1,2,3\n")
    assert len(out) == 2
    assert parser.errors.wrong_columns == 0, parser.errors.nonzero()
    assert parser.errors.non_numeric == 2, parser.errors.nonzero()
    # a line of numbers that lacks columns still is one
    parser.feed(b"3000,1,2\n")
    assert parser.errors.wrong_columns == 1


# --------------------------------------------------------------------------- replay's input


def test_replay_of_a_csv_says_to_import_it(tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "some.csv"
    src.write_text("t_us,x,y,z\n" + "".join(f"{i * 20_000},0,0,1024\n" for i in range(50)))
    rc, _out, err = _run(["replay", str(src), "--out", str(tmp_path / "r.mcap")], capsys)
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert "recal import" in err and "repair" not in err, err
    assert not (tmp_path / "r.mcap").exists()
    binary = tmp_path / "photo.jpg"  # neither text nor MCAP: no hint that does not fit
    binary.write_bytes(b"\xff\xd8\xff\xe0" + bytes(range(256)))
    rc, _out, err = _run(["export", str(binary), "--csv", str(tmp_path / "o.csv")], capsys)
    assert rc == 2 and "not an MCAP" in err and "repair" not in err and "import" not in err, err


def test_an_unfinished_mcap_keeps_the_repair_hint(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    whole = tmp_path / "whole.mcap"
    rc, _out, err = _run(["simulate", "--out", str(whole), "--hours", "0.01"], capsys)
    assert rc == 0, err
    cut = tmp_path / "cut.mcap"
    data = whole.read_bytes()
    cut.write_bytes(data[:len(data) // 2])  # a writer killed half-way
    rc, _out, err = _run(["replay", str(cut), "--out", str(tmp_path / "r.mcap")], capsys)
    assert rc == 2 and f"recal repair {cut}" in err and "recal import" not in err, err


# --------------------------------------------------------------------------- demo


def test_the_demo_headline_is_the_settled_error_not_the_warm_up_mean() -> None:
    """The figure right after "calibrated" is the settled one; the whole-run mean, warm-up
    included, comes last and says so."""
    from recal.commands.demo import _print_summary

    lines: list[str] = []
    errors = {"offset_true_mg": [1.0] * 3, "offset_est_mg": [1.0] * 3, "offset_err_mg": [0.0] * 3,
              "gain_true_pct": [0.0] * 3, "gain_est_pct": [0.0] * 3, "gain_err_pct": [0.0] * 3,
              "uncalibrated_err_rms_mg": 61.0, "accel_err_rms_mg_all": 24.8,
              "accel_err_rms_mg_second_half": 7.0, "noise_floor_rms_mg": 6.9}
    _print_summary({"errors": errors, "started_from": "prior"}, lines.append)
    line = next(x for x in lines if "a_true" in x)
    after = line.split("calibrated", 1)[1]
    assert after.index("7.0 mg") < after.index("24.8 mg"), line
    assert "warm-up" in line[line.index("24.8") - 40:], line


# --------------------------------------------------------------------------- export's counts


def test_export_counts_uncalibrated_and_bootstrapping_apart() -> None:
    from recal.commands.export import StatusCounts
    from recal.core.status import Status
    from recal.samples import CalibratedBatch

    status = np.array([Status.UNCALIBRATED] * 3 + [Status.BOOTSTRAPPING] * 5
                      + [Status.CALIBRATED] * 7 + [Status.HELD] * 2, np.uint8)
    n = len(status)
    counts = StatusCounts()
    counts.add(CalibratedBatch(np.arange(n) * 20_000, np.zeros((n, 3)), np.zeros(n, bool),
                               np.zeros(n), status, np.ones(n)))
    d = counts.to_dict()
    assert d["samples_uncalibrated"] == 3
    assert d["samples_bootstrapping"] == 5
    assert d["samples_not_calibrated"] == 10
    assert d["samples_by_status"] == {"uncalibrated": 3, "bootstrapping": 5, "calibrated": 7,
                                      "held": 2}
    assert counts.line().startswith("7 samples out calibrated, 10 with another status"), \
        counts.line()


# --------------------------------------------------------------------------- hindsight help


def test_hindsight_help_names_the_columns_its_csv_has(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sim = tmp_path / "s.mcap"
    assert _run(["simulate", "--out", str(sim), "--hours", "0.05"], capsys)[0] == 0
    out = tmp_path / "h.csv"
    rc, _out, err = _run(["hindsight", str(sim), "--out", str(out), "--quiet"], capsys)
    assert rc == 0, err
    header = out.read_text().splitlines()[0]
    assert header == "t_us,x_g,y_g,z_g,status,sigma_mg"
    with pytest.raises(SystemExit):
        main(["hindsight", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert header in text, text


# --------------------------------------------------------------------------- static tables

FACES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
PHONE1 = Path(__file__).resolve().parents[2] / "shared" / "data" / "static_positions" / "phone1.csv"


def _table(path: Path, v: np.ndarray) -> Path:
    path.write_text("x,y,z\n" + "".join(f"{a:.3f},{b:.3f},{c:.3f}\n" for a, b, c in v))
    return path


def test_static_on_one_pose_warns_and_exits_non_zero(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """2 000 rows of one pose determine no axis angle: said on the console and in the JSON,
    and the exit status is 1 (the angles printed would mean nothing)."""
    rng = np.random.default_rng(0)
    v = np.array([0.1, 0.05, 0.99]) * 1024 + rng.normal(0, 6, (2000, 3))
    js = tmp_path / "r.json"
    rc, out, err = _run(["static", str(_table(tmp_path / "one.csv", v)), "--json", str(js)],
                        capsys)
    assert rc == 1, (out, err)
    assert "do not cover enough orientations" in err and "do not cover enough" in out, err
    import json
    report = json.loads(js.read_text())
    assert report["usable"] is False and "do not cover enough" in report["warning"]


def test_static_on_a_real_table_is_usable(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = _run(["static", str(PHONE1), "--json", str(tmp_path / "r.json")], capsys)
    assert rc == 0 and "do not cover" not in out + err, (out, err)
    import json
    assert json.loads((tmp_path / "r.json").read_text())["usable"] is True


def test_static_minimax_on_many_rows_matches_the_fit_on_all_constraints() -> None:
    """The minimax fit works on the rows that can be worst and adds any row that exceeds
    the bound: the same optimum as one problem with every row, in a fraction of the time."""
    from recal.core import static

    rng = np.random.default_rng(4)
    dirs = rng.normal(size=(3000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    k = np.array([[1000.0, 8, -5], [0, 1030, 6], [0, 0, 990]])
    v = dirs @ k.T + np.array([20.0, -15, 30]) + rng.normal(0, 1.5, (3000, 3))
    fit = static.fit_unknown_orientations(v, np.ones(len(v), bool), None, loss="minimax")
    l2 = static.fit_unknown_orientations(v, np.ones(len(v), bool), None, loss="l2")
    worst, worst_l2 = fit.rel_norm_error.max(), l2.rel_norm_error.max()
    assert worst <= worst_l2  # never worse than where it started
    # no row is above the bound the fit reports (the subset missed none)
    assert fit.params["determination"] > 1e-3
