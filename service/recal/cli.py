"""`recal`: the command line. Thin: every command parses arguments and calls one function.

Every command of recal runs from here (the daemon is ``recal run``, a calibration node on its
own ``recal node``; their arguments and help texts are in `recal.cli_arguments`); nothing
imports this module. An error the user can act on
(`recal.errors.RecalError`, or an OSError: a file or port the system refused) ends in one line
on stderr and exit status 2; anything else is a bug and shows its traceback. The commands
import the modules that do their work when they run: ``recal --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from recal import cli_arguments
from recal.errors import RecalError, UsageError

if TYPE_CHECKING:
    from recal.config.sensor_options import SensorOptions

__all__ = ["build_parser", "main"]


def _new_output(path: str, overwrite: bool, source: str | None = None) -> None:
    """Never write onto the input ``source``; replace an existing file only when asked (a
    recording may hold days of data)."""
    if source is not None:
        from recal.io.recording import refuse_input_as_output

        refuse_input_as_output(path, source)
    if Path(path).exists() and not overwrite:
        raise UsageError(f"{path} exists; pass --overwrite to replace it")


def _report_paths(*paths: str | None) -> None:
    """Where reports and figures go must be a directory that exists: said before the work,
    not after minutes of it."""
    for path in paths:
        if path is not None and not Path(path).resolve().parent.is_dir():
            raise UsageError(f"{path}: no directory {Path(path).parent} to write it in")


# --- simulate --------------------------------------------------------------------------------
def _simulated_effects(a: argparse.Namespace, rng: np.random.Generator) -> dict[str, object]:
    """The sensor fields of the effects' options (`effects.SimOption`): three values with a
    random sign each, or one number; the signs drawn in the options' order."""
    from recal.core.effects import sim_options

    out: dict[str, object] = {}
    for o in sim_options():
        value = getattr(a, _dest(o.flag)) / o.divisor
        out[o.field] = tuple(np.full(3, value) * rng.choice([-1, 1], 3)) if o.per_axis else value
    return out


def _dest(flag: str) -> str:
    """argparse's attribute name for a long option."""
    return flag.lstrip("-").replace("-", "_")


def _cmd_simulate(a: argparse.Namespace) -> int:
    from recal.commands.import_csv import write_raw_messages
    from recal.io import csv_table
    from recal.io.recording_writer import FILE_TO_FILE_FLUSH_S, RecordingWriter
    from recal.sim import wearer as sim

    rng = np.random.default_rng(a.seed)
    sensor = sim.SensorSpec.random(rng, offset_mg=a.offset_mg, gain_pct=a.gain_pct,
                                   cross_axis_deg=a.cross_axis_deg)
    sensor = replace(
        sensor, noise_g=a.noise_mg / 1e3,
        counts_per_g=None if a.counts_per_g <= 0 else a.counts_per_g,
        **_simulated_effects(a, rng), temp_channel=a.temp_name, supply_channel=a.supply_name)
    if a.sensor_type:  # the type's fields (counts per g, zero-g, ADC) over the options'
        if a.sensor_type not in sim.SENSOR_TYPES:
            raise UsageError(f"--sensor-type must be one of {', '.join(sim.SENSOR_TYPES)}, "
                             f"not {a.sensor_type!r}")
        sensor = replace(sensor, **sim.SENSOR_TYPES[a.sensor_type])
    temp = {k: v for k, v in (("temp_wander_c", a.temp_wander_c),
                              ("temp_wander_tau_min", a.temp_tau_min)) if v is not None}
    wearer = sim.WearerSpec(upright_only=a.upright_only, always_aux=a.aux, **temp)
    out = Path(a.out)
    if out.suffix.lower() not in (".csv", ".mcap"):
        raise UsageError(f"--out must end in .mcap or .csv, not {out.name!r}")
    _new_output(a.out, a.overwrite)
    res = sim.simulate(a.hours, a.rate, a.seed, sensor, wearer)
    if out.suffix.lower() == ".csv":
        csv_table.write_raw_csv(out, res.raw)
    else:
        with RecordingWriter(out, overwrite=True, flush_interval_s=FILE_TO_FILE_FLUSH_S) as w:
            write_raw_messages(w, a.sensor_id, res.raw)
    truth = out.with_suffix(".truth.npz")
    sim.save_truth(truth, res)
    print(f"wrote {out} ({len(res.raw)} samples, {a.hours:g} h at {a.rate:g} Hz, channels "
          f"{list(res.raw.aux_names) or 'none'}) and ground truth {truth}")
    return 0


# --- import / export -------------------------------------------------------------------------
def _cmd_import(a: argparse.Namespace) -> int:
    from recal.commands.import_csv import import_csv

    _new_output(a.out, a.overwrite, a.input)
    print("\n".join(import_csv(a.input, a.out, units=a.units, rate_hz=a.rate,
                                sensor_id=a.sensor_id, quiet=a.quiet)))
    return 0


def _cmd_export(a: argparse.Namespace) -> int:
    from recal.commands.export import export_csv

    _new_output(a.csv, a.overwrite, a.input)
    _report_paths(a.json)
    report, lines = export_csv(a.input, a.csv, a.sensor_id, a.topic)
    print("\n".join(lines))
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=2))
    return 0


# --- static ----------------------------------------------------------------------------------
#: from this many rows on, `recal static` says on stderr that it is fitting (seconds, not
#: instant: one Gauss-Newton solve over every row, then the minimax rounds)
STATIC_SAY_ROWS = 50_000


def _cmd_static(a: argparse.Namespace) -> int:
    from recal.commands import static as st

    _report_paths(a.json)
    v = st.read_static_table(a.input)
    if len(v) >= STATIC_SAY_ROWS:  # a fit of many rows takes a while: say what is going on
        print(f"recal static: fitting {len(v)} rows ...", file=sys.stderr, flush=True)
    report, lines = st.static_report(v, st.parse_rows(a.fit_rows, len(v)),
                                     known_orientations=a.known_orientations, g=a.g,
                                     full=not a.diagonal, loss=a.loss)
    print("\n".join(lines))
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=2))
    if not report["usable"]:  # said on stderr too: a script reading stdout must not miss it
        print(f"recal static: warning: {report['warning']}", file=sys.stderr)
        return 1
    return 0


# --- discover --------------------------------------------------------------------------------
def _cmd_discover(a: argparse.Namespace) -> int:
    from recal.commands import discover as dr
    from recal.commands.static import read_static_table
    from recal.config import load_model_file
    from recal.core.discovery import DiscoveryConfig
    from recal.core.discovery_data import data_from_table
    from recal.io.sources import open_recording, recording_kind, source_lines

    _report_paths(a.json, a.write_model, a.plots)
    path = Path(a.input)
    kind = recording_kind(path)  # by content, never by extension
    src = None
    if kind == "csv" and a.rate is None and not dr.csv_has_time(path):
        data = data_from_table(read_static_table(a.input))  # one still row per pose
    elif kind == "mcap":
        data = dr.data_from_recording(path, a.sensor_id, a.window_s)[0]
    else:  # a CSV time series or a device file: two or three passes, with a bar
        src = open_recording(path, a.sensor_id, a.rate, a.units)
        if src.device is not None:  # the device and what reading it did, before the table
            print("\n".join(source_lines(src)))
        with _sample_bar("discover (passes)", a.quiet) as bar:
            data = dr.data_from_source(src, a.window_s, bar.update)
    model, p = None, None
    if a.model:
        model, prior = load_model_file(a.model)
        p = prior.mean if prior is not None else None
    try:
        dr.run(data, model=model, p=p, cfg=DiscoveryConfig(blocks=a.blocks),
               json_path=a.json, plots_dir=a.plots, model_path=a.write_model,
               source=str(path), device=src.metadata if src and src.device else None)
    except RuntimeError as e:  # matplotlib missing for --plots
        raise UsageError(str(e)) from None
    return 0


def _sample_bar(desc: str, quiet: bool) -> Any:
    """A progress bar in samples on a terminal (none in a pipe, a log or --quiet)."""
    from tqdm import tqdm

    return tqdm(unit="sample", unit_scale=True, desc=desc, leave=False,
                disable=quiet or None)


# --- hindsight -------------------------------------------------------------------------------
def _cmd_hindsight(a: argparse.Namespace) -> int:
    from tqdm import tqdm

    from recal.commands import hindsight as hf
    from recal.commands.span_windows import default_threads
    from recal.config import load_model_file
    from recal.io.sources import open_recording

    if Path(a.input).is_dir():
        return _hindsight_folder(a)
    folder_only = [f"--{k}" for k in ("samples", "workers", "scheduler", "verify")
                   if getattr(a, k) not in (None, False)]
    if folder_only:
        raise UsageError(f"{', '.join(folder_only)}: for a folder input only")
    if a.threads is not None and a.threads < 1:
        raise UsageError(f"--threads must be at least 1, not {a.threads}")
    if a.out is None and a.json is None:
        raise UsageError("hindsight writes --out (every sample calibrated), --json (the "
                         "calibration alone) or both: give at least one")
    if a.out is not None:
        _new_output(a.out, a.overwrite, a.input)
    _report_paths(a.json, a.out)
    model = load_model_file(a.model)[0] if a.model else None
    threads = a.threads or default_threads()
    src = open_recording(a.input, a.sensor_id, a.rate, a.units, threads=threads)
    # passes over the input (module doc of recal.commands.hindsight; a device file's reader
    # gives the rate, so no first pass): samples read, in all
    passes = (3 if a.out is not None else 2) - (src.device is not None)
    total = passes * len(src.device) if src.device is not None else None
    with tqdm(unit="sample", unit_scale=True, desc=f"hindsight ({passes} passes)", leave=False,
              disable=a.quiet or None, total=total) as bar:
        summary = hf.calibrate_file(src, a.out, model, a.overwrite, bar.update,
                                    threads=threads)
    if a.json:
        Path(a.json).write_text(json.dumps(summary, indent=2, default=str))
    print("\n".join(hf.summary_lines(summary)))
    return 0


def _hindsight_folder(a: argparse.Namespace) -> int:
    """`recal hindsight DIR --out OUTDIR` (`commands.study`): exit 0 when every recording was
    calibrated, 1 when some failed."""
    from recal.commands.study import run_study
    from recal.commands.study.plan import options_for

    file_only = [f"--{k}" for k in ("json", "overwrite", "threads")
                 if getattr(a, k) not in (None, False)]
    if file_only:
        raise UsageError(f"{', '.join(file_only)}: for a file input only (a folder's results "
                         "are OUTDIR/summary.csv and .json; done files are kept)")
    if a.out is None:
        raise UsageError("a folder input needs --out OUTDIR (each file's calibration and "
                         "summary.csv go there)")
    if a.scheduler is not None and a.workers is not None:
        raise UsageError("--workers is for local processes; a Dask cluster has its own")
    if a.model is not None and not Path(a.model).is_file():
        raise UsageError(f"--model {a.model}: no such file")
    options = options_for(a.model, a.samples, a.sensor_id, a.rate, a.units)
    return run_study(a.input, a.out, options, workers=a.workers, scheduler=a.scheduler,
                     verify=a.verify, quiet=a.quiet).exit_code


# --- replay / repair / run / demo / router ---------------------------------------------------
def _cmd_replay(a: argparse.Namespace) -> int:
    from recal.commands.replay import replay, replay_lines

    _new_output(a.out, a.overwrite, a.input)
    _report_paths(a.json)
    summary = replay(a.input, a.out, model=a.model, config=a.config, progress=not a.quiet,
                     overwrite=a.overwrite)
    if a.json:
        Path(a.json).write_text(json.dumps(summary, indent=2, default=str))
    print("\n".join(replay_lines(summary)))
    return 0


def _cmd_repair(a: argparse.Namespace) -> int:
    from recal.io.repair import repair

    _new_output(a.out, a.overwrite, a.input)
    rep = repair(a.input, a.out)
    print(f"recovered {rep.messages_recovered} messages into {a.out}"
          f" ({'input was truncated' if rep.truncated else 'input was complete'})")
    for topic, n in sorted(rep.messages_per_topic.items()):
        print(f"  {topic}: {n}")
    return 0


def _sensor_options(a: argparse.Namespace) -> SensorOptions:
    from recal.config.sensor_options import SensorOptions

    return SensorOptions(rate_hz=a.rate, aux_names=a.aux_names, prior=a.prior,
                         counts_per_g=a.counts_per_g, zero_g=a.zero_g)


def _cmd_run(a: argparse.Namespace) -> int:
    """The daemon, with the options of `_add_run_arguments`."""
    from recal.daemon.gateway import run_gateway

    return run_gateway(a.config, a.port, a.sensor_id, a.mcap, model_path=a.model,
                       batch_s=None if a.batch_ms is None else a.batch_ms / 1e3,
                       sensor_options=_sensor_options(a))


def _cmd_node(a: argparse.Namespace) -> int:
    from recal.daemon.remote_node import run_node

    return run_node(a.config, a.sensor_id, a.mcap, a.model, accept_any=a.accept_any,
                    max_sensors=a.max_sensors)


def _cmd_demo(a: argparse.Namespace) -> int:
    from recal.commands.demo import run_demo

    return run_demo(a.seconds, a.out, seed=a.seed)


def _cmd_router(a: argparse.Namespace) -> int:
    import zenoh

    from recal.config import read_config_text
    from recal.io.router import run_router

    if a.config is not None:  # missing, a directory, binary: said here, naming the file
        read_config_text(Path(a.config), "Zenoh JSON5 config")
    try:
        return run_router(listen_endpoints=a.listen or None, config_file=a.config)
    except zenoh.ZError as e:  # bad endpoint or config file, port in use
        # Zenoh appends the Rust source location (not for the user) and may draw the place of
        # a syntax error over several lines: one line
        said = " ".join(str(e).split(" at /")[0].split())
        with_config = f" (config {a.config})" if a.config is not None else ""
        raise UsageError(f"cannot start the router{with_config}: {said}") from None


#: the function that runs each command, by its name
_COMMANDS: dict[str, cli_arguments.Command] = {
    "demo": _cmd_demo,
    "run": _cmd_run,
    "node": _cmd_node,
    "replay": _cmd_replay,
    "simulate": _cmd_simulate,
    "static": _cmd_static,
    "discover": _cmd_discover,
    "hindsight": _cmd_hindsight,
    "import": _cmd_import,
    "export": _cmd_export,
    "repair": _cmd_repair,
    "router": _cmd_router,
}


def build_parser() -> argparse.ArgumentParser:
    """The parser of every command line (recal.cli_arguments), each command bound to its
    function here."""
    return cli_arguments.build_parser(_COMMANDS)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    import logging

    from recal.console import install_logging

    handler = install_logging()  # warnings as bare stderr lines, each kind rate-limited
    try:
        return _dispatch(args.func, args)
    finally:  # main() called in a process that goes on (tests) leaves logging as it was
        logging.getLogger().removeHandler(handler)


def _dispatch(func: Callable[[argparse.Namespace], int | None], args: argparse.Namespace
              ) -> int:
    """Run a command: what the user can act on is one line and exit status 2; a bug (any
    other exception) keeps its traceback."""
    try:
        return int(func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (RecalError, OSError) as e:
        msg: object = e
        if isinstance(e, OSError) and e.filename:
            msg = f"{e.filename}: {e.strerror or e}"
        print(f"recal: error: {msg}", file=sys.stderr)
        return 2

