"""`recal node` on Zenoh loopback without the fleet config, fed a crafted stream on a configured
id: the node must stay able to save what it produces and keep its time base.

Real parts only: a `recal router` child process on 127.0.0.1, Zenoh client sessions,
``run_node`` in a thread, checkpoints and the MCAP read back. Every wait is bounded.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from polling import wait_for
from recal.core.pipeline import Pipeline
from recal.daemon.checkpoint_store import load_checkpoint
from recal.io import recording as rec
from recal.io.bus import key
from recal.io.messages import encode_raw
from recal.samples import RawBatch
from recal.sim import wearer as sim
from test_security import RATE_HZ, NodeThread, node_config, plain_client, status_of

SID = "wrist"
YEARS_17_US = 17 * 365 * 86_400 * 10**6


def _crafted(after_us: int, n: int) -> RawBatch:
    """A crude fake: a clock 17 years ahead, zero-g 5120 counts, 'gravity' of 1 count."""
    rng = np.random.default_rng(9)
    t = after_us + YEARS_17_US + np.arange(n, dtype=np.int64) * round(1e6 / RATE_HZ)
    dirs = np.repeat(rng.normal(size=(n // 500 + 1, 3)), 500, axis=0)[:n]
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    return RawBatch(t, 5120.0 + dirs + rng.normal(0.0, 0.5, (n, 3)), np.zeros((n, 0)), ())


def test_a_crafted_stream_on_a_configured_id_leaves_the_node_able_to_save(
        plain_router: str, tmp_path: Path) -> None:
    """A wearer's stream, then a fake one on the same id: the 17-year clock jump is refused
    (event and line), no estimate outside the configured bounds is kept (the checkpoint's),
    and every checkpoint save succeeds: the last one holds every sample and a time within
    minutes of the real stream's end."""
    real = sim.simulate(8 / 60, RATE_HZ, 3, sim.SensorSpec()).raw
    fake = _crafted(int(real.t_us[-1]), 20_000)
    cfg = node_config(tmp_path, (SID,), checkpoint={"dir": str(tmp_path / "ck"),
                                                     "interval_s": 0.2,
                                                     "after_update_s": 0.1})
    node_bus, gw = plain_client(plain_router), plain_client(plain_router)
    try:
        nt = NodeThread(cfg, node_bus, tmp_path / "node.mcap")
        try:
            pub = gw.publisher(key(SID, "raw"))
            assert pub.wait_for_subscribers(10)
            sent = 0
            for part in (real, fake):
                for i in range(0, len(part), 500):  # bounded: one pass over each
                    assert pub.put(encode_raw(SID, part[i:i + 500]))
                sent += len(part)
                assert wait_for(lambda s=sent: (status_of(gw, SID) or {}).get("node", {}).get(
                    "samples") == s, 30)
            ck = tmp_path / "ck" / f"{SID}.json"
            assert wait_for(lambda: (load_checkpoint(ck) or {}).get("pipeline", {}).get(
                "counts", {}).get("samples") == sent, 10), "\n".join(nt.lines)
        finally:
            assert nt.close() == 0
    finally:
        node_bus.close()
        gw.close()
    assert not [x for x in nt.lines if "not saved" in x], nt.lines
    assert any("device time jumped" in x for x in nt.lines), nt.lines
    doc = load_checkpoint(tmp_path / "ck" / f"{SID}.json")
    assert doc is not None and doc["t_us"] - int(real.t_us[-1]) < 3600 * 10**6
    kinds = [obj["kind"] for _, obj, _ in rec.iter_json(tmp_path / "node.mcap",
                                                        f"/{SID}/events")]
    assert "time_jump_refused" in kinds, kinds
    # no estimate outside the configured bounds is kept: the checkpoint's model is this sensor's
    kept = Pipeline.from_state_dict(doc["pipeline"])
    assert abs(kept.model.s0 - 1024.0) < 0.5 * 1024, kept.model.s0
    # every calibrated sample keeps the stamp its raw message had, the refused jump included
    cal = rec.read_all_calibrated(tmp_path / "node.mcap", SID)
    assert cal.t_dev is not None
    np.testing.assert_array_equal(cal.t_dev, np.concatenate([real.t_us, fake.t_us]))
    assert np.all(np.diff(cal.t_us) > 0) and cal.t_us[-1] - real.t_us[-1] < 3600 * 10**6
