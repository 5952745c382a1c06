"""The device file kinds recal recognises: one entry per kind, each with its sniff test (on
content, never the extension), its reader (None: recognised, not readable yet) and a name a
person knows it by. The first entry whose test passes names the file; a new kind is one entry.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from recal.io.device_files import actigraph, actigraph_own, axivity, geneactiv
from recal.io.device_files.parsed import Parsed
from recal.io.device_files.probe import Probe

__all__ = ["KINDS", "DeviceKind", "kind_of", "sniff"]


@dataclass(frozen=True)
class DeviceKind:
    kind: str
    family: str
    name: str
    test: Callable[[Probe], bool]
    #: (path read, path shown, lenient, threads) -> Parsed; threads: the .cwa decoder's (the
    #: other kinds are read by actfast, on one)
    read: Callable[[Path, Path, bool, int], Parsed] | None
    why_not: str = ""


KINDS: tuple[DeviceKind, ...] = (
    DeviceKind("axivity_cwa", "axivity", "Axivity AX3/AX6 .cwa", axivity.sniff_cwa,
               axivity.read),
    DeviceKind("geneactiv_bin", "geneactiv", "GENEActiv .bin", geneactiv.sniff_geneactiv,
               geneactiv.read),
    DeviceKind("genea_bin", "geneactiv", "Genea .bin (the older Genea format)",
               geneactiv.sniff_genea, None, "its reader (actfast) refuses this format"),
    # the two .gt3x kinds actfast cannot read (recal's own decoder) come before the one it can
    DeviceKind("actigraph_gt3x_activity2", "actigraph",
               "ActiGraph .gt3x of ACTIVITY2 records (ActiGraph Link, CentrePoint)",
               actigraph.sniff_activity2, actigraph_own.read),
    DeviceKind("actigraph_gt3x_nhanes", "actigraph",
               "ActiGraph .gt3x of the NHANES era (activity.bin, no log.bin)",
               actigraph.sniff_nhanes, actigraph_own.read),
    DeviceKind("actigraph_gt3x", "actigraph", "ActiGraph .gt3x", actigraph.sniff_gt3x,
               actigraph.read),
)


def kind_of(path: str | Path) -> DeviceKind | None:
    probe = Probe(Path(path))
    return next((k for k in KINDS if k.test(probe)), None)


def sniff(path: str | Path) -> str | None:
    """The kind of device file by its content ('axivity_cwa', 'geneactiv_bin',
    'actigraph_gt3x', ... see KINDS), None for anything else."""
    k = kind_of(path)
    return None if k is None else k.kind
