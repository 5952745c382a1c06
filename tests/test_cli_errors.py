"""Bad configuration and bad command lines: `recal ...` as a real process.

Every case must end with exactly one line on stderr, ``recal: error: <what, naming the file or
key>``, a non-zero exit status, nothing on stdout and never a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from recal.errors import InputError
from recal.io.recording_writer import RecordingWriter
from recal.sim.pty_device import PtyDevice
from recal.sim.wearer import simulate

NO_ZENOH = "[zenoh]\nenabled = false\n"
FILES: dict[str, bytes] = {
    "syntax.toml": b"[pipeline\nthreshold_g = 0.01\n",
    "unknown_table.toml": b"[pipelin]\nthreshold_g = 0.01\n",
    "unknown_key.toml": b"[pipeline]\ntreshold_g = 0.01\n",
    "wrong_type.toml": b'[pipeline]\nthreshold_g = "high"\n',
    "negative.toml": b"[pipeline]\nthreshold_g = -0.01\n",
    "above_nyquist.toml": b"[pipeline]\nlp_hz = 80\n",
    "zero_grid.toml": b"[pipeline.buffer]\ngrid = 0\n",
    "wrong_list.toml": b"[zenoh]\nlisten = \"tcp/127.0.0.1:7447\"\n",
    "bad_sensor_id.toml": b"[[sensors]]\nid = \"a/b\"\nport = \"/dev/null\"\n",
    "no_zenoh.toml": NO_ZENOH.encode(),
    "portless.toml": (NO_ZENOH + '[[sensors]]\nid = "wrist"\n').encode(),
    "not_utf8.csv": b"t_us,x,y,z\n1,2,3,4\n\xff\xfe,1,2,3\n",
    "empty.csv": b"",
    "no_axes.csv": b"t_us,a,b,c\n1,2,3,4\n",
    "duplicate.csv": b"t_us,x,y,z,x\n1,2,3,4,5\n",
    "all_bad.csv": b"t_us,x,y,z\n1,2,3\nfoo,bar,baz,qux\n",
    "no_time.csv": b"x,y,z\n1,2,3\n",
    "negative_time.csv": b"t_us,x,y,z\n-5,1,2,3\n",
    "static_bad.csv": b"x,y,z\n1,2\n",
    "static_ok.csv": b"x,y,z\n" + b"".join(f"{x},{y},{z}\n".encode() for x, y, z in (
        (1, 0, 0), (0, 1, 0), (0, 0, 1), (-1, 0, 0), (0, -1, 0), (0, 0, -1))),
    "a_file": b"not a directory\n",
    "no_effects.json": b'{"model": {"effects": []}}',
}

# (case id, arguments, expected exit status, fragment the one line must contain)
CASES = [
    # a bad config file
    ("toml syntax", ["run", "--config", "syntax.toml"], 2, "syntax.toml: not valid TOML"),
    ("unknown table", ["run", "--config", "unknown_table.toml"], 2, "pipelin: unknown key"),
    ("unknown key", ["run", "--config", "unknown_key.toml"], 2, "treshold_g: unknown key"),
    ("wrong type", ["run", "--config", "wrong_type.toml"], 2,
     "[pipeline] threshold_g: expected a number"),
    ("wrong list", ["run", "--config", "wrong_list.toml"], 2, "listen"),
    ("out of range", ["run", "--config", "negative.toml"], 2,
     "[pipeline]: invalid pipeline settings: threshold_g must be positive"),
    ("above nyquist", ["run", "--config", "above_nyquist.toml"], 2,
     "hp_hz and lp_hz must lie between 0 and half the sample rate"),
    ("buffer out of range", ["run", "--config", "zero_grid.toml"], 2,
     "grid, per_cell and merge_max must be at least 1"),
    ("bad sensor id", ["run", "--config", "bad_sensor_id.toml"], 2, "invalid sensor id"),
    ("missing config", ["run", "--config", "nowhere.toml"], 2, "nowhere.toml: no such file"),
    ("replay bad config", ["replay", "{mcap}", "--out", "o.mcap", "--config", "syntax.toml"],
     2, "syntax.toml: not valid TOML"),
    ("node bad config", ["node", "--config", "wrong_type.toml"], 2, "threshold_g"),
    ("node without zenoh", ["node", "--config", "no_zenoh.toml"], 2,
     "a calibration node takes its samples from Zenoh, but the config's [zenoh] enabled = false"),
    ("missing model", ["replay", "{mcap}", "--out", "o.mcap", "--model", "nowhere.json"], 2,
     "nowhere.json"),
    ("model without effects", ["replay", "{mcap}", "--out", "o.mcap", "--model",
                               "no_effects.json"], 2, "a model needs at least one effect"),
    # a missing port
    ("no port at all", ["run", "--config", "no_zenoh.toml"], 2, "no sensors"),
    ("port is a regular file", ["run", "--config", "no_zenoh.toml", "--port", "no_time.csv"],
     2, "port no_time.csv is not a character device"),
    ("port is a directory", ["run", "--config", "no_zenoh.toml", "--port", "."], 2,
     "port . is a directory"),
    ("port is not a tty", ["run", "--config", "no_zenoh.toml", "--port", "/dev/null"], 2,
     "port /dev/null is a character device but not a terminal"),
    ("port url unknown", ["run", "--config", "no_zenoh.toml", "--port", "bogus://x"], 2,
     "port bogus://x: invalid URL"),
    ("sensor without port", ["run", "--config", "portless.toml"], 2, "'wrist' has no port"),
    ("ports and ids differ", ["run", "--config", "no_zenoh.toml", "--port", "{tty}",
                              "--sensor-id", "a", "--sensor-id", "b"], 2, "1 ports but 2"),
    ("one port twice", ["run", "--config", "no_zenoh.toml", "--port", "{tty}", "--port",
                        "{tty}"], 2, "is given to two sensors"),
    ("invalid id on the command line", ["run", "--config", "no_zenoh.toml", "--port", "{tty}",
                                        "--sensor-id", "a b"], 2, "invalid sensor id 'a b'"),
    ("reserved id", ["run", "--config", "no_zenoh.toml", "--port", "{tty}", "--sensor-id",
                     "gateway"], 2, "invalid sensor id 'gateway'"),
    ("one id twice", ["run", "--config", "no_zenoh.toml", "--port", "{tty}", "--port", "{mcap}",
                      "--sensor-id", "a", "--sensor-id", "a"], 2, "sensor id 'a' is given twice"),
    # an MCAP path that cannot be written (root may write anywhere, but not under a file)
    ("run mcap under a file", ["run", "--config", "no_zenoh.toml", "--port", "{tty}",
                               "--mcap", "a_file/x.mcap"], 1, "cannot open the recording"),
    ("run mcap in /proc", ["run", "--config", "no_zenoh.toml", "--port", "{tty}",
                           "--mcap", "/proc/recal.mcap"], 1, "/proc/recal.mcap"),
    ("replay out under a file", ["replay", "{mcap}", "--out", "a_file/o.mcap", "--quiet"], 2,
     "a_file"),
    ("replay out exists", ["replay", "{mcap}", "--out", "no_time.csv", "--quiet"], 2,
     "no_time.csv exists; pass --overwrite to replace it"),
    ("simulate out under a file", ["simulate", "--out", "a_file/s.mcap", "--hours", "0.001"], 2,
     "a_file"),
    ("export csv under a file", ["export", "{mcap}", "--csv", "a_file/o.csv", "--topic", "raw"],
     2, "a_file"),
    ("repair out under a file", ["repair", "{mcap}", "--out", "a_file/o.mcap"], 2, "a_file"),
    # an output that is the input
    ("repair onto its input", ["repair", "{mcap}", "--out", "{mcap}"], 2,
     "ok.mcap is the input ok.mcap; write the output elsewhere"),
    ("replay onto its input", ["replay", "{mcap}", "--out", "{mcap}", "--overwrite"], 2,
     "ok.mcap is the input ok.mcap"),
    ("export onto its input", ["export", "{mcap}", "--csv", "{mcap}", "--topic", "raw"], 2,
     "ok.mcap is the input ok.mcap"),
    ("import onto its input", ["import", "no_time.csv", "--out", "no_time.csv", "--rate", "50"],
     2, "no_time.csv is the input no_time.csv"),
    # an output that exists (replaced only with --overwrite)
    ("simulate out exists", ["simulate", "--out", "{mcap}", "--hours", "0.001"], 2,
     "ok.mcap exists; pass --overwrite to replace it"),
    ("import out exists", ["import", "no_time.csv", "--out", "{mcap}", "--rate", "50"], 2,
     "ok.mcap exists; pass --overwrite"),
    ("export out exists", ["export", "{mcap}", "--csv", "no_time.csv", "--topic", "raw"], 2,
     "no_time.csv exists; pass --overwrite"),
    ("repair out exists", ["repair", "{mcap}", "--out", "no_time.csv"], 2,
     "no_time.csv exists; pass --overwrite"),
    # a missing input file
    ("replay missing input", ["replay", "nowhere.mcap", "--out", "o.mcap"], 2, "nowhere.mcap"),
    ("import missing input", ["import", "nowhere.csv", "--out", "o.mcap"], 2, "nowhere.csv"),
    ("export missing input", ["export", "nowhere.mcap", "--csv", "o.csv"], 2, "nowhere.mcap"),
    ("export unknown sensor", ["export", "{mcap}", "--csv", "o.csv", "--sensor-id", "nosuch"], 2,
     "ok.mcap has no sensor 'nosuch' (it has: s1)"),
    ("discover unknown sensor", ["discover", "{mcap}", "--sensor-id", "nosuch"], 2,
     "no raw samples for sensor 'nosuch' (sensors: s1)"),
    ("repair missing input", ["repair", "nowhere.mcap", "--out", "o.mcap"], 2, "nowhere.mcap"),
    ("static missing input", ["static", "nowhere.csv"], 2, "nowhere.csv"),
    ("replay not an mcap", ["replay", "all_bad.csv", "--out", "o.mcap"], 2,
     "a CSV becomes one with: recal import all_bad.csv --out RECORDING.mcap"),
    ("export not an mcap", ["export", "all_bad.csv", "--csv", "o.csv"], 2,
     "all_bad.csv is not an MCAP recording but text"),
    # a bad CSV
    ("csv not utf-8", ["import", "not_utf8.csv", "--out", "o.mcap"], 2,
     "not_utf8.csv: not UTF-8"),
    ("csv empty", ["import", "empty.csv", "--out", "o.mcap"], 2, "empty.csv: no header row"),
    ("csv no axes", ["import", "no_axes.csv", "--out", "o.mcap"], 2, "no_axes.csv: no axis"),
    ("csv duplicate", ["import", "duplicate.csv", "--out", "o.mcap"], 2, "duplicate column"),
    ("csv all rows bad", ["import", "all_bad.csv", "--out", "o.mcap"], 2,
     "all_bad.csv: no valid rows (2 bad, first at lines 2, 3)"),
    ("csv no time", ["import", "no_time.csv", "--out", "o.mcap"], 2, "no time column"),
    ("csv negative time", ["import", "negative_time.csv", "--out", "o.mcap"], 2,
     "negative_time.csv: times must be"),
    ("csv units clash", ["import", "no_time.csv", "--out", "o.mcap", "--units", "parsecs"], 2,
     "--units"),
    ("static bad rows", ["static", "static_bad.csv"], 2, "static_bad.csv"),
    ("report in no directory", ["discover", "{mcap}", "--write-model", "nodir/m.json"], 2,
     "nodir/m.json: no directory nodir to write it in"),
    ("static report in no directory", ["static", "static_ok.csv", "--json", "nodir/s.json"], 2,
     "no directory nodir"),
    ("static too few rows", ["static", "static_ok.csv", "--fit-rows", "1-3"], 2,
     "3 fitted rows cannot determine the 9 parameters of the full model"),
    ("static not utf-8", ["static", "not_utf8.csv"], 2, "not_utf8.csv: not UTF-8"),
    # the command line itself
    ("unknown command", ["frobnicate"], 2, "invalid choice"),
    ("missing argument", ["import", "no_time.csv"], 2, "required: --out"),
    ("not a number", ["simulate", "--out", "s.mcap", "--hours", "two"], 2, "--hours"),
    ("demo not positive", ["demo", "--seconds", "0"], 2,
     "argument --seconds: must be a positive number, not 0"),
    ("router bad endpoint", ["router", "--listen", "tcp/999.1.1.1:1"], 2,
     "cannot start the router"),
    ("router missing config", ["router", "--config", "nowhere.json5"], 2,
     "nowhere.json5: no such file"),
]


@contextlib.contextmanager
def _workdir_in(root: Path) -> Iterator[Path]:
    """The files every case may read, a small valid recording, and a real pty for --port."""
    for name, data in FILES.items():
        (root / name).write_bytes(data)
    raw = simulate(0.002, 50.0, 1).raw
    with RecordingWriter(root / "ok.mcap", overwrite=True) as writer:
        writer.write_raw("s1", raw, int(raw.t_us[0]) * 1000)
    with PtyDevice(str(root / "ttyOK"), "ascii"):
        yield root


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    with _workdir_in(tmp_path_factory.mktemp("cli")) as root:
        yield root


def _args(args: list[str], workdir: Path) -> list[str]:
    return [a.replace("{mcap}", "ok.mcap").replace("{tty}", str(workdir / "ttyOK"))
            for a in args]


def _main(args: list[str], capfd: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """``recal.cli.main`` in this process (the console script's code); an exception other
    than SystemExit escaping it would be the traceback, and fails the test by itself."""
    from recal.cli import main

    capfd.readouterr()
    try:
        status = main(args)
    except SystemExit as exc:  # argparse
        status = exc.code if isinstance(exc.code, int) else 1
    out, err = capfd.readouterr()
    return status, out, err


def _assert_one_error_line(status: int, out: str, err: str, want_status: int,
                           fragment: str) -> None:
    lines = err.splitlines()
    assert "Traceback" not in err + out, err
    assert len(lines) == 1, err
    assert lines[0].startswith("recal: error: ") and fragment in lines[0], lines[0]
    assert status == want_status, (status, lines[0])
    assert out == "", out


@pytest.mark.parametrize(("args", "status", "fragment"), [c[1:] for c in CASES],
                         ids=[c[0] for c in CASES])
def test_one_clear_error_line_and_no_traceback(
        workdir: Path, args: list[str], status: int, fragment: str,
        capfd: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(workdir)
    _assert_one_error_line(*_main(_args(args, workdir), capfd), status, fragment)


# One case of each kind again as a real `python -m recal` process: what a user sees.
AS_PROCESS = ["toml syntax", "port is a regular file", "run mcap under a file",
              "csv all rows bad", "missing argument", "router bad endpoint"]


@pytest.mark.parametrize("case", AS_PROCESS)
def test_as_a_real_process(workdir: Path, case: str) -> None:
    _, args, status, fragment = next(c for c in CASES if c[0] == case)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    done = subprocess.run([sys.executable, "-m", "recal", *_args(args, workdir)], cwd=workdir,
                          env=env, capture_output=True, text=True, timeout=60)
    _assert_one_error_line(done.returncode, done.stdout, done.stderr, status, fragment)


def test_nothing_is_left_behind_by_a_failed_start(
        tmp_path: Path, capfd: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A start that fails on its recording, port or model writes no file and no checkpoint
    (in a directory of its own: the shared one has seen every other case first)."""
    with _workdir_in(tmp_path) as root:
        monkeypatch.chdir(root)
        before = set(os.listdir(root))
        for case in ("run mcap under a file", "port is a regular file", "missing model",
                     "csv all rows bad"):
            args = next(c[1] for c in CASES if c[0] == case)
            status, _, _ = _main(_args(args, root), capfd)
            assert status != 0
        assert set(os.listdir(root)) == before


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    from recal.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


@pytest.mark.parametrize("command", sorted(_subcommands()))
def test_every_command_explains_itself(command: str,
                                       capfd: pytest.CaptureFixture[str]) -> None:
    """`recal <command> --help`: exit 0, the usage, a description, at least one example that
    calls the command, every option explained; never a traceback (a bare % in a help string
    once made argparse raise on `recal simulate --help`)."""
    status, out, err = _main([command, "--help"], capfd)
    assert status == 0 and err == "", err
    assert out.startswith(f"usage: recal {command}"), out[:200]
    description = out.split("\n\n")[1]
    assert len(description.split()) >= 10, description
    examples = out.split("examples:\n", 1)[1].splitlines()
    assert examples and all(e.startswith(f"  recal {command}") for e in examples), examples
    unexplained = [a.dest for a in _subcommands()[command]._actions if not a.help]
    assert unexplained == [], unexplained


def test_an_input_named_as_output_is_left_intact(tmp_path: Path,
                                                 capfd: pytest.CaptureFixture[str],
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """`recal repair x.mcap --out x.mcap` once left 405 bytes of a 942 kB recording: every
    command that reads a file and writes another refuses to write onto its input, and one
    that would replace an existing file does so only with --overwrite."""
    with _workdir_in(tmp_path) as root:
        monkeypatch.chdir(root)
        before = {name: (root / name).read_bytes() for name in ("ok.mcap", "no_time.csv")}
        for case in ("repair onto its input", "replay onto its input", "export onto its input",
                     "import onto its input", "simulate out exists", "import out exists",
                     "export out exists", "repair out exists"):
            args = next(c[1] for c in CASES if c[0] == case)
            status, _, _ = _main(_args(args, root), capfd)
            assert status == 2
        assert {name: (root / name).read_bytes() for name in before} == before


@pytest.mark.parametrize("bug", [KeyError("t_us"), ValueError("shapes differ"),
                                 TypeError("not a number")], ids=lambda e: type(e).__name__)
def test_a_bug_keeps_its_traceback(bug: Exception, capfd: pytest.CaptureFixture[str],
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """Only what the user can act on (recal.errors.RecalError, OSError) is one line: a plain
    KeyError or ValueError is a bug, and must not read as a user's mistake."""
    from recal import cli

    def broken(_args: argparse.Namespace) -> int:
        raise bug

    monkeypatch.setitem(cli._COMMANDS, "repair", broken)
    with pytest.raises(type(bug)):
        cli.main(["repair", "in.mcap", "--out", "out.mcap"])
    assert "recal: error" not in capfd.readouterr().err


@pytest.mark.parametrize("error", [InputError("bad table"),
                                   FileNotFoundError(2, "No such file", "in.mcap")],
                         ids=lambda e: type(e).__name__)
def test_what_the_user_can_act_on_is_one_line(error: Exception,
                                              capfd: pytest.CaptureFixture[str],
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    from recal import cli

    def refused(_args: argparse.Namespace) -> int:
        raise error

    monkeypatch.setitem(cli._COMMANDS, "repair", refused)
    status, out, err = _main(["repair", "in.mcap", "--out", "out.mcap"], capfd)
    want = "bad table" if isinstance(error, ValueError) else "in.mcap: No such file"
    _assert_one_error_line(status, out, err, 2, want)
