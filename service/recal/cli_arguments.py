"""`recal`'s command-line arguments: every command's options, its help line, its longer
description and its examples; the parser sets ``func`` to the function that runs the command
(given by recal.cli, which imports what each command needs when it runs)."""

from __future__ import annotations

import argparse
import textwrap
from collections.abc import Callable, Mapping
from typing import NoReturn

import numpy as np

from recal.core.effects import sim_options

__all__ = ["Command", "build_parser"]

#: what runs a command: the parsed arguments in, the exit status out
Command = Callable[[argparse.Namespace], int]


class _Parser(argparse.ArgumentParser):
    """Argument mistakes as one ``recal: error:`` line too (argparse would add the usage)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"recal: error: {message} (see {self.prog} --help)\n")


def _positive(text: str) -> float:
    """argparse type: a finite number above 0."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (x > 0 and np.isfinite(x)):
        raise argparse.ArgumentTypeError(f"must be a positive number, not {text}")
    return x


def _names(text: str) -> tuple[str, ...]:
    """argparse type: comma-separated channel names ('' for none)."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"a name is given twice in {text!r}")
    return names


def _add_run_arguments(p: argparse.ArgumentParser) -> None:
    """The daemon's options (`recal run`)."""
    p.add_argument("--port", action="append", default=[], help="serial port (repeatable)")
    p.add_argument("--sensor-id", action="append", default=[], help="id per --port")
    p.add_argument("--config", help="service config (TOML), e.g. configs/gateway.toml")
    p.add_argument("--mcap", help="MCAP output path (default from config)")
    p.add_argument("--model", help="model file written by `recal discover --write-model`")
    p.add_argument("--batch-ms", type=float, default=None,
                   help="handle what arrived every this many ms instead of at once: less CPU, "
                   "up to this much more latency (default: the config's batch_ms, 0 = at once; "
                   "100 for a battery-powered gateway)")
    p.add_argument("--rate", type=_positive, metavar="HZ",
                   help="the sensors' sample rate (as the config's rate_hz); with it, lines "
                   "without a time column (x,y,z[,aux]) are stamped first arrival + i / rate")
    p.add_argument("--aux-names", type=_names, metavar="A,B",
                   help="the auxiliary channels after x,y,z, by name (as the config's "
                   "aux_names; '' for none; default: the device's header)")
    p.add_argument("--prior", metavar="NAME", help="a named prior (the config's priors_file "
                   "or [priors]; without --config, configs/sensor-priors.toml)")
    p.add_argument("--counts-per-g", type=_positive, metavar="N",
                   help="nominal sensitivity in raw units per g (the prior's counts_per_g)")
    p.add_argument("--zero-g", type=float, metavar="N",
                   help="the reading at 0 g, raw units, every axis (the prior's zero_g)")


def _add_node_arguments(ap: argparse.ArgumentParser, config_help: str, mcap_help: str,
                        model_help: str) -> None:
    """`recal node`'s options."""
    ap.add_argument("--config", help=config_help)
    _add_serving_arguments(ap)
    ap.add_argument("--mcap", help=mcap_help)
    ap.add_argument("--model", help=model_help)


def _add_serving_arguments(ap: argparse.ArgumentParser) -> None:
    """``--sensor-id``, ``--accept-any``, ``--max-sensors`` (``recal node``)."""
    ap.add_argument("--sensor-id", action="append", default=[],
                    help="serve this sensor (repeatable; default: the config's [[sensors]])")
    ap.add_argument("--accept-any", action="store_const", const=True, default=None,
                    help="also serve sensors nobody named, whoever publishes them "
                         "(default: config [node] accept_any, false)")
    ap.add_argument("--max-sensors", type=int, metavar="N", default=None,
                    help="with --accept-any, serve at most N sensors not named "
                         "(default: config [node] max_sensors, 16)")


# --- parser ----------------------------------------------------------------------------------
#: what each command does, at more length than the one-line help, and how it is called
_ABOUT: dict[str, tuple[str, tuple[str, ...]]] = {
    "demo": ("Runs the main job with nothing attached: a simulated sensor with known offsets "
             "and gains writes ASCII lines to a pseudo-terminal faster than real time, the "
             "daemon reads it, logs it to MCAP and publishes it calibrated on Zenoh (a peer on "
             "127.0.0.1), the demo's own Zenoh session times the calibrated batches, and a "
             "summary compares the estimate with the truth. Stops by itself. Every run starts "
             "fresh from the prior in a new folder of its own (a temporary one, or "
             "run-<UTC time> inside --out DIR), never resumes an earlier run's checkpoint and "
             "writes nothing else; the MCAP, summary.json and the checkpoint stay there. The "
             "progress line is redrawn in place on a terminal, a plain line every 5 s otherwise.",
             ("recal demo", "recal demo --seconds 20 --out /tmp/demo")),
    "run": ("The daemon: reads every serial port, publishes raw and calibrated samples on "
            "Zenoh (recal/<sensor>/...), logs everything to MCAP (default: an auto-named file "
            "in recordings/; an existing file is never overwritten) and checkpoints each "
            "sensor's calibration in the state folder ([checkpoint] dir, else systemd's "
            "$STATE_DIRECTORY, $XDG_STATE_HOME/recal or ~/.local/state/recal; printed at "
            "start), where it also locks each sensor id. Runs until Ctrl-C or SIGTERM; after "
            "a crash, `recal repair` recovers the log and the checkpoint resumes the "
            "calibration. A port is opened exclusively (a second daemon on it stops at once, "
            "naming the holder) and without discarding what the device already sent; a "
            "missing device is waited for. Lines without a time column (x,y,z) need --rate; "
            "device clocks that wrap, count milliseconds or restart are unwrapped, recognised "
            "and reported.",
            ("recal run --port /dev/ttyACM0 --sensor-id wrist",
             "recal run --config configs/gateway.toml",
             "recal run --port /dev/ttyUSB0 --rate 50 --aux-names vdd --prior sim-1024",
             "recal run --port /dev/ttyACM0 --port /dev/ttyACM1 --sensor-id l --sensor-id r")),
    "node": ("A calibration node without serial ports: takes recal/*/raw from gateways that run "
             "with run_nodes = false (through a `recal router` or as peers), and publishes "
             "calibrated, body, calibration and events for each sensor it serves: those of the "
             "config's [[sensors]] or --sensor-id; other ids are counted and dropped unless "
             "--accept-any (at most --max-sensors of them). Runs until Ctrl-C or SIGTERM.",
             ("recal node --config configs/gateway.toml --mcap node.mcap",
              "recal node --config configs/fleet/node.toml",
              "recal node --config node.toml --accept-any --max-sensors 8")),
    "replay": ("Runs the raw topic of a recording through the same calibration node as the "
               "daemon (detector, windows, estimator, correction) and writes raw, calibrated, "
               "body, plot, calibration states and events to a new MCAP. No Zenoh, no clocks: "
               "the same input gives the same output. A device file (.cwa, .bin, .gt3x) "
               "streams every sample through the node, logged at its sample time.",
               ("recal replay recordings/wearer-10min.mcap --out replayed.mcap --json r.json",
                "recal replay in.mcap --out out.mcap --model model.json")),
    "simulate": ("A wearer-like recording (still postures and movement) sensed by a sensor "
                 "with random offsets and gains and the effects asked for, with the ground truth "
                 "beside it (FILE.truth.npz). The same seed gives the same recording.",
                 ("recal simulate --out wearer.mcap --hours 2",
                  "recal simulate --out temp.mcap --hours 1 --offset-tc-mg-per-c 1.5 --aux")),
    "static": ("Lab calibration from still positions, one row per position: a full sensitivity "
               "matrix and offsets (Bragge; Georgieva's non-orthogonal axes) fitted so that "
               "every row's norm is 1 g, with the worst row's relative norm error over all rows "
               "and over the fitted rows.",
               ("recal static ../shared/data/static_positions/phone1.csv --fit-rows 1-20",)),
    "hindsight": ("Calibrates a recording already on disk as the batch tools do (one fit on "
                  "the whole recording, every sample corrected with it), with the live "
                  "detector and windows. Without --model it first selects the effects the "
                  "recording shows as recal discover does (same windows, same held-out rule: "
                  "cross-axis terms, a supply or temperature channel, drift...) and reports "
                  "them with the held-out error before -> after; --model fixes the model. "
                  "Parameters the recording's poses cannot determine are held at nominal and "
                  "named. Writes raw, calibrated and the fit (MCAP) or "
                  "t_us,x_g,y_g,z_g,status,sigma_mg (CSV: the status of each sample, "
                  "calibrated or held, and its predicted error in mg). A device file (.cwa, "
                  ".bin, .gt3x) is read with true sample times and its device's metadata goes "
                  "into the output and --json. With --json and no --out it writes the "
                  "calibration alone (no pass over the samples to correct them). Given a "
                  "folder, it calibrates every recording under it (one row per file in "
                  "OUTDIR/summary.csv, failures as rows; a second run skips what is done) on "
                  "local processes or a Dask cluster: docs/study.md.",
                  ("recal hindsight recordings/wearer-10min.mcap --out calibrated.mcap",
                   "recal hindsight in.mcap --out out.csv --model model.json --json fit.json",
                   "recal hindsight week.cwa --json fit.json",
                   "recal hindsight study/ --out calibrated/ --workers 2")),
    "discover": ("Fits the model, looks at what it leaves in the residual, scores candidate "
                 "effects (offsets, gains or ratiometric scaling that follow an auxiliary "
                 "channel such as temperature or supply; cross-axis terms; non-linearity; "
                 "offset drift in time) on held-out time blocks, adds what helps and reports "
                 "the held-out error before -> after. "
                 "--write-model saves the extended model for run/replay --model. Takes "
                 "device files (.cwa, .bin, .gt3x) as well.",
                 ("recal discover recordings/wearer-temp-30min.mcap --json report.json",
                  "recal discover table.csv --write-model model.json")),
    "import": ("A CSV time series (a time column t_us, t_ms or t_s, or none with --rate; x, y, "
               "z or x_<unit>, y_<unit>, z_<unit>; any auxiliary columns by name) to an MCAP raw "
               "topic that replay and discover read. Bad rows are counted and skipped. A "
               "device file (Axivity .cwa/.cwa.gz, GENEActiv .bin, ActiGraph .gt3x) is read "
               "with true sample times; its device's metadata goes into the recording.",
               ("recal import log.csv --out log.mcap --units g",
                "recal import log.csv --out log.mcap --rate 100",
                "recal import wrist.cwa --out wrist.mcap")),
    "export": ("The calibrated (default) or raw samples of one sensor of a recording (default: "
               "the first) to CSV.",
               ("recal export replayed.mcap --csv calibrated.csv",
                "recal export in.mcap --csv raw.csv --topic raw --sensor-id wrist")),
    "repair": ("Copies every complete message of a truncated or unfinished MCAP (a killed "
               "daemon, a full disk) to a new, finished file; the input is never changed.",
               ("recal repair recordings/recal-20261122T030000Z.mcap --out fixed.mcap",)),
    "router": ("A Zenoh router for several gateways and calibration nodes on different "
               "machines (loopback only unless --listen says otherwise). Runs until Ctrl-C or "
               "SIGTERM.",
               ("recal router", "recal router --listen tcp/127.0.0.1:7447")),
}


def _add_command(sub: argparse._SubParsersAction, name: str, help_: str
                 ) -> argparse.ArgumentParser:
    """A subcommand with its one-line help in `recal --help`, and the longer description and
    examples of _ABOUT in `recal <name> --help`."""
    text, examples = _ABOUT[name]
    return sub.add_parser(name, help=help_, description=textwrap.fill(text, 79),
                          epilog="examples:\n" + "\n".join(f"  {e}" for e in examples),
                          formatter_class=argparse.RawDescriptionHelpFormatter)


def build_parser(commands: Mapping[str, Command]) -> argparse.ArgumentParser:
    """recal's parser; each subcommand's ``func`` default is ``commands[<its name>]``."""
    p = _Parser(
        prog="recal",
        description="Streaming in-use recalibration of triaxial accelerometers: whenever the "
                    "sensor is quasi-static its calibrated vector must be 1 g long (Lötters "
                    "1998); recal estimates offsets, sensitivities and more from that, live.")
    from recal import __version__
    p.add_argument("--version", action="version", version=f"recal {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = _add_command(sub, "demo", "the main job on an embedded default: a simulated sensor "
                       "on a pseudo-terminal, the daemon, Zenoh on loopback, a summary")
    s.add_argument("--seconds", type=_positive, default=45.0, help="how long to run (default 45)")
    s.add_argument("--out", "--out-dir", metavar="DIR", default=None,
                   help="make this run's folder (run-<UTC time>) inside DIR, created if need be "
                        "(default: a new temporary folder)")
    s.add_argument("--seed", type=int, default=7,
                   help="simulator seed: the sensor's errors and the wearer (default 7)")
    s.set_defaults(func=commands["demo"])

    s = _add_command(sub, "run", "the daemon: serial ports -> Zenoh -> calibration -> MCAP")
    _add_run_arguments(s)
    s.set_defaults(func=commands["run"])

    s = _add_command(sub, "node", "a calibration node on its own: subscribes to recal/*/raw "
                       "(gateways elsewhere run with run_nodes = false)")
    _add_node_arguments(s, "service config (TOML): [zenoh], [[sensors]] priors, [pipeline]",
                        "also log raw and calibrated here",
                        "model file for every sensor (recal discover --write-model)")
    s.set_defaults(func=commands["node"])

    s = _add_command(sub, "replay", "re-run the raw topic of a recording through the "
                       "calibration node (same code as the daemon, no Zenoh)")
    s.add_argument("input", help="recording (.mcap) or device file (Axivity .cwa/.cwa.gz, "
                   "GENEActiv .bin, ActiGraph .gt3x), recognised by content")
    s.add_argument("--out", required=True, help="output recording (.mcap)")
    s.add_argument("--model", help="model file (effects and starting values)")
    s.add_argument("--config", help="service config (TOML) for priors and settings")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    s.add_argument("--json", help="write the whole summary (parameters, counts, alignment per "
                   "sensor) as JSON here")
    s.set_defaults(func=commands["replay"])

    s = _add_command(sub, "simulate", "make a wearer-like recording with ground truth")
    s.add_argument("--out", required=True, help="FILE.mcap or FILE.csv (truth: FILE.truth.npz)")
    s.add_argument("--hours", type=float, default=2.0, help="length (default 2)")
    s.add_argument("--rate", type=float, default=50.0, help="sample rate in Hz (default 50)")
    s.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    s.add_argument("--sensor-id", default="sim0", help="sensor id in the MCAP (default sim0)")
    s.add_argument("--offset-mg", type=float, default=50.0,
                   help="offsets drawn in +-this (default 50)")
    s.add_argument("--gain-pct", type=float, default=3.0,
                   help="gain errors drawn in +-this (default 3)")
    s.add_argument("--cross-axis-deg", type=float, default=0.0,
                   help="misalignment +-this (default 0)")
    s.add_argument("--noise-mg", type=float, default=4.0,
                   help="white noise per axis (default 4)")
    s.add_argument("--counts-per-g", type=float, default=1024.0,
                   help="ADC scale (default 1024); 0: no ADC, readings in g")
    s.add_argument("--sensor-type", metavar="TYPE",
                   help="a sensor people plug in: adxl335-adc12, mma7260-adc14 (analog, "
                        "unsigned ADC), digital-2g ... digital-16g, adxl345-10bit, phone-ms2 "
                        "(floats); its counts per g, zero-g and ADC replace --counts-per-g")
    for o in sim_options():  # each effect's own (offset, gain in temperature, ...)
        s.add_argument(o.flag, type=float, default=0.0, help=o.help.replace("%", "%%"))
    s.add_argument("--temp-name", default="temp_c", help="name of the temperature channel")
    s.add_argument("--supply-name", default="vdd_v", help="name of the supply channel")
    s.add_argument("--aux", action="store_true", help="always write temperature and supply")
    s.add_argument("--upright-only", action="store_true", help="never lie down (tilt <= 30 deg)")
    s.add_argument("--temp-wander-c", type=float,
                   help="sd of the slow temperature wander, deg C (default: the simulator's)")
    s.add_argument("--temp-tau-min", type=float,
                   help="correlation time of that wander, minutes (default: the simulator's)")
    s.add_argument("--overwrite", action="store_true", help="replace the output if it exists")
    s.set_defaults(func=commands["simulate"])

    s = _add_command(sub, "static", "lab calibration from a table of still positions")
    s.add_argument("input", help="CSV with columns x,y,z (any unit) one row per position")
    s.add_argument("--fit-rows", help="rows to fit, e.g. 1-20 or 1-6,9 (default all)")
    s.add_argument("--known-orientations", action="store_true",
                   help="rows lie on faces: fit K and O linearly (Bragge)")
    s.add_argument("--g", type=float, help="local gravity in the table's unit (only names it)")
    s.add_argument("--diagonal", action="store_true", help="no cross-axis terms (6 params)")
    s.add_argument("--loss", choices=("minimax", "l2"), default="minimax",
                   help="least worst row (default) or least squares")
    s.add_argument("--json", help="write the report as JSON here")
    s.set_defaults(func=commands["static"])

    s = _add_command(sub, "discover", "find the effects the model lacks: fit, residual, "
                       "candidate effects scored on held-out time blocks, before -> after")
    s.add_argument("input", help="recording (.mcap), device file (Axivity .cwa/.cwa.gz, "
                   "GENEActiv .bin, ActiGraph .gt3x), CSV time series (t_us/t_ms/t_s, x, y, z, "
                   "channels), or a static table (x, y, z, one still row per pose); recognised "
                   "by content")
    s.add_argument("--json", help="write the report (effects_selected, heldout_error_mg, "
                   "steps, ...) here")
    s.add_argument("--plots", metavar="DIR", help="write PNG figures here (needs matplotlib)")
    s.add_argument("--write-model", metavar="MODEL.json",
                   help="the extended model and starting values for run/replay --model")
    s.add_argument("--model", help="start from this model file instead of offsets + gains")
    s.add_argument("--sensor-id", help="which sensor of a recording (default: the only one)")
    s.add_argument("--blocks", type=int, default=10, help="held-out time blocks (default 10)")
    s.add_argument("--window-s", type=float, help="window length for short still poses "
                   "(default 2 s, as the daemon)")
    s.add_argument("--rate", type=float, help="sample rate of a CSV without a time column")
    s.add_argument("--units", choices=("counts", "g", "ms2"), help="unit of a CSV's x, y, z")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=commands["discover"])

    s = _add_command(sub, "hindsight", "calibrate a recording on disk with hindsight: one fit "
                       "on all of it, every sample corrected (as the batch tools do); or "
                       "every recording under a folder")
    s.add_argument("input", help="recording (.mcap), device file (Axivity .cwa/.cwa.gz, "
                   "GENEActiv .bin, ActiGraph .gt3x) or CSV time series (t_us/t_ms/t_s, x, y, "
                   "z, channels), recognised by content; or a folder: every recording under "
                   "it (a study)")
    s.add_argument("--out", help="FILE.mcap (raw, calibrated, the fit) or FILE.csv; without "
                   "it, only the calibration is written (--json) and no sample is; for a "
                   "folder input, OUTDIR (each file's calibration at its relative path, "
                   "summary.csv and summary.json)")
    s.add_argument("--model", help="model file (recal discover --write-model): fixes the model; "
                   "default: the effects recal discover selects on the same windows")
    s.add_argument("--sensor-id", help="which sensor of a recording (default: the only one)")
    s.add_argument("--json", help="write the fit (parameters, sd, held, windows, discovery) here "
                   "(--out, --json or both)")
    s.add_argument("--rate", type=float, help="sample rate of a CSV without a time column")
    s.add_argument("--units", choices=("counts", "g", "ms2"), help="unit of a CSV's x, y, z")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    s.add_argument("--threads", type=int, metavar="N", help="a device file: find its windows "
                   "on N threads (the same windows; default: the cores, at most 8)")
    s.add_argument("--samples", choices=("mcap", "csv"), help="folder: also write each file's "
                   "calibrated samples (default: the calibrations alone)")
    s.add_argument("--workers", type=int, metavar="N", help="folder: local worker processes "
                   "(default: the cores, fewer if the memory cannot hold them)")
    s.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="folder: run on this Dask "
                   "cluster's workers instead (needs recal[cluster])")
    s.add_argument("--verify", action="store_true", help="folder: a done file counts as done "
                   "only if its SHA-256 is unchanged too (default: size and mtime)")
    s.set_defaults(func=commands["hindsight"])

    s = _add_command(sub, "import", "CSV (t_us, t_ms or t_s, x, y, z, aux...) or device file "
                       "-> MCAP raw topic")
    s.add_argument("input", help="CSV file or device file (Axivity .cwa/.cwa.gz, GENEActiv "
                   ".bin, ActiGraph .gt3x), recognised by content")
    s.add_argument("--out", required=True, help="MCAP file to write")
    s.add_argument("--units", choices=("counts", "g", "ms2"),
                   help="unit of x, y, z (default: the header's x_<unit> names, else "
                   "counts; must agree with them)")
    s.add_argument("--rate", type=float, help="sample rate when the CSV has no time column")
    s.add_argument("--sensor-id", help="sensor id (default: a device file's device and id, "
                   "else imported)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.add_argument("--overwrite", action="store_true", help="replace the output if it exists")
    s.set_defaults(func=commands["import"])

    s = _add_command(sub, "export", "MCAP -> CSV of calibrated (default) or raw samples")
    s.add_argument("input", help="recording (.mcap)")
    s.add_argument("--csv", required=True, help="CSV file to write")
    s.add_argument("--topic", choices=("calibrated", "raw"), default="calibrated",
                   help="which samples (default calibrated)")
    s.add_argument("--sensor-id", help="which sensor (default: the first)")
    s.add_argument("--json", help="write the counts here: rows, samples_by_status, "
                   "samples_uncalibrated, samples_bootstrapping, samples_not_calibrated "
                   "(any status but calibrated)")
    s.add_argument("--overwrite", action="store_true", help="replace the output if it exists")
    s.set_defaults(func=commands["export"])

    s = _add_command(sub, "repair", "recover every complete message of a truncated MCAP")
    s.add_argument("input", help="the damaged recording (.mcap), read only")
    s.add_argument("--out", required=True, help="the repaired recording to write")
    s.add_argument("--overwrite", action="store_true", help="replace the output if it exists")
    s.set_defaults(func=commands["repair"])

    s = _add_command(sub, "router", "a Zenoh router for multi-gateway deployments")
    s.add_argument("--listen", action="append", default=[],
                   help="endpoint (default tcp/127.0.0.1:7447; repeatable)")
    s.add_argument("--config", help="Zenoh JSON5 config, e.g. configs/zenoh-router.json5")
    s.set_defaults(func=commands["router"])
    return p
