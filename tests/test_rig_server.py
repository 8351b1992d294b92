"""End to end in real time: `combined-reality virtual-rig` on a pseudo-terminal, SerialRig/CanRig on the host.

Every server is a subprocess, as a real rig would be. Nothing here asserts how fast the
machine is: the checks are on sequence numbers, timestamps, what the rig reports it
applied, and the host's own accounting.
"""
import gc
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from combined_reality.cli import main
from combined_reality.live import PositionProgram
from hw.can_rig import CanRig
from hw.realtime import make_normal, make_realtime
from hw.rig import Status, bounded
from hw.serial_rig import SerialRig

ROOT = Path(__file__).resolve().parents[1]
CFG = ROOT / "configs" / "cyl_a_32x100.toml"

# real time is tested with two busy processes beside (conftest.busy_machine)
pytestmark = pytest.mark.usefixtures("busy_machine")


class Server:
    """`combined-reality virtual-rig ...` in a subprocess; `path` is the first line it prints."""

    def __init__(self, tmp_path: Path, *args: str, name: str = "server"):
        self.err_path = tmp_path / f"{name}.err"
        self._err = open(self.err_path, "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "combined_reality", "virtual-rig", "--config", str(CFG),
                                      *args], stdout=subprocess.PIPE, stderr=self._err, text=True, cwd=ROOT)
        self.path = self.proc.stdout.readline().strip()
        assert self.path.startswith("/dev/"), self.stderr()

    def stderr(self) -> str:
        return self.err_path.read_text()  # the child writes it directly

    def stop(self, sig=signal.SIGTERM) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        code = self.proc.wait(timeout=20)
        self._err.close()
        return code

    def injected(self) -> tuple[int, int]:
        m = re.search(r"faults injected: (\d+) frames dropped, (\d+) corrupted", self.stderr())
        return (int(m.group(1)), int(m.group(2))) if m else (0, 0)


@pytest.fixture
def servers(tmp_path):
    started = []

    def start(*args, name="server"):
        s = Server(tmp_path, *args, name=name)
        started.append(s)
        return s

    yield start
    for s in started:
        if s.proc.poll() is None:
            s.proc.kill()
            s.proc.wait()


def closed_loop(rig, cyl, duration, *, seed=1, quiet_after=None, until=None):
    """Position control on the measured samples; returns samples and the command sent per sample seq."""
    program = PositionProgram(cyl, duration + 5, seed=seed)
    samples, replies = [], {}
    # a full collection over everything earlier tests left behind (hypothesis) can pause
    # this process for more than the rig's 50 ms watchdog: a real-time host freezes its
    # long-lived objects before it starts the loop
    gc.collect()
    gc.freeze()
    # like a live session: the loop and the link's reader at real-time priority where granted
    granted = make_realtime(5) is None
    try:
        _loop(rig, program, samples, replies, duration, quiet_after, until)
    finally:
        gc.unfreeze()
        if granted:
            make_normal()
    return samples, replies


def _loop(rig, program, samples, replies, duration, quiet_after, until):
    rig.start()
    rig.realtime(5)
    t_end = time.monotonic() + duration
    while time.monotonic() < t_end:
        if until is not None and until(samples):
            break
        s = rig.read(timeout=0.1)
        if s is None:
            continue
        samples.append(s)
        if quiet_after is not None and s.t - samples[0].t > quiet_after:
            continue  # the host goes silent but keeps listening
        u = bounded(program.command(s.t, s.x))
        rig.send(u)
        replies[s.seq] = u


def check_stream(samples, replies, stats, quantise):
    seq = np.array([s.seq for s in samples])
    t = np.array([s.t for s in samples])
    dt = np.diff(t)
    assert np.all(np.diff(seq) == 1), "sequence gaps"
    assert np.all(dt > 0)
    assert 0.98e-3 < np.median(dt) < 1.02e-3
    assert np.std(dt) > 2e-6  # the rig's clock has jitter and the samples carry it
    sent = {k: quantise(u) for k, u in replies.items()}
    # healthy: a missed deadline (the machine's load) or the rig's soft stroke limit (a late
    # host overshooting) may show; on a busy machine the rig's watchdog too, when the host was
    # held up for 50 ms (the rig says so, and the valve is centred meanwhile)
    allowed = Status.OVERRUN | Status.SOFT_LIMIT | (Status.WATCHDOG if stats.rig_errors else 0)
    assert all(s.status & ~allowed == 0 for s in samples), [s for s in samples if s.status & ~allowed]
    assert all(s.u_applied == 0.0 for s in samples if s.status & Status.WATCHDOG)
    free = [s for s in samples[1:] if not s.status & Status.SOFT_LIMIT]
    # timing contract: sample k+1 reports the reply to sample k, unless that reply was late
    mismatch = [s for s in free if s.u_applied != sent[s.seq - 1]]
    earlier = set(sent.values()) | {0.0}  # the rig starts with the valve centred
    assert all(s.u_applied in earlier for s in mismatch), [s for s in mismatch if s.u_applied not in earlier]
    # the host's own count agrees; it cannot see a late reply equal to the one before (a
    # saturated command), it also counts late replies the soft limit overrode, and the
    # replies to the last samples, cut by stop()
    alike = sum(sent[k] == sent.get(k - 1) for k in sent)
    limited = len(samples) - 1 - len(free)
    assert len(mismatch) <= stats.commands_late <= len(mismatch) + alike + limited + 3


@dataclass
class Session:
    """A host on a `virtual-rig` server for one closed loop: what it saw, how the server ended."""

    server: Server
    rig: SerialRig | CanRig
    samples: list  # read in the loop
    replies: dict  # command sent per sample seq
    events: list  # the rig's one-line fault messages
    tail: list  # samples that arrived after the loop, read after stop()
    code: int  # the server's exit status

    @property
    def received(self) -> list:
        """Every sample the host's link accounted for (its stats count gaps between all of them)."""
        return self.samples + self.tail


def session(servers, cyl, duration, *server_args, stop_signal=signal.SIGTERM, **loop) -> Session:
    """`virtual-rig *server_args` (--serial or --can) and a host on it: start, closed loop, stop; then the
    server is stopped."""
    srv = servers(*server_args)
    events = []
    if "--can" in server_args:
        rig = CanRig(srv.path, interface="slcan", sleep_after_open=0.05, on_event=events.append)
    else:
        rig = SerialRig(srv.path, on_event=events.append)
    samples, replies = closed_loop(rig, cyl, duration, **loop)
    rig.stop()
    tail = []
    while (s := rig.read(timeout=0)) is not None:
        tail.append(s)
    return Session(srv, rig, samples, replies, events, tail, srv.stop(stop_signal))


def test_serial_closed_loop_at_1khz_loses_nothing(servers, cyl_a):
    r = session(servers, cyl_a, 3.0, "--serial", "--seed", "2")
    assert r.code == 0, r.server.stderr()
    st = r.rig.stats
    assert len(r.samples) > 2000
    assert st.samples_lost == 0 and st.frames_corrupt == 0 and st.bytes_discarded == 0 and st.reconnects == 0
    check_stream(r.samples, r.replies, st, lambda u: float(np.float32(u)))
    assert np.ptp([s.x for s in r.samples]) > 0.01
    # the only messages a healthy link may give are about the machine's load
    assert all("missed the rig's next tick" in e or e.startswith("rig reports sampling deadline missed")
               for e in r.events), r.events
    assert "streaming stopped by the host" in r.server.stderr()


def test_slcan_closed_loop_at_1khz_loses_nothing(servers, cyl_a):
    r = session(servers, cyl_a, 3.0, "--can", "--seed", "3", stop_signal=signal.SIGINT)
    assert r.code == 0, r.server.stderr()
    st = r.rig.stats
    assert len(r.samples) > 2000
    assert st.samples_lost == 0 and st.frames_corrupt == 0
    check_stream(r.samples, r.replies, st, r.rig.codec.quantise_u)
    assert np.ptp([s.x for s in r.samples]) > 0.01


def test_corrupted_bytes_are_rejected_counted_and_reported(servers, cyl_a):
    r = session(servers, cyl_a, 2.0, "--serial", "--corrupt", "0.05")
    assert r.code == 0
    _, corrupted = r.server.injected()
    st = r.rig.stats
    assert corrupted > 20 and st.frames_corrupt >= 0.8 * corrupted
    # a corrupted sample is a lost sample; nothing damaged gets through
    assert 0.8 * corrupted - 5 <= st.samples_lost <= corrupted
    assert sum(np.diff([s.seq for s in r.received]) - 1) == st.samples_lost
    assert all(-1e-3 < s.x < 0.101 and 5e4 < s.p1 < 1e6 and 5e4 < s.p2 < 1e6 for s in r.samples)
    sent = {float(np.float32(u)) for u in r.replies.values()} | {0.0}
    assert all(s.u_applied in sent for s in r.samples)
    lines = [e for e in r.events if "corrupted frame" in e]
    assert 1 <= len(lines) <= 4 and all(re.fullmatch(r"serial link: \d+ corrupted frames? rejected in the "
                                                      r"last second", e) for e in lines)


def test_dropped_frames_show_as_sequence_gaps(servers, cyl_a):
    r = session(servers, cyl_a, 2.0, "--serial", "--drop", "0.02")
    assert r.code == 0
    dropped, _ = r.server.injected()
    st = r.rig.stats
    assert dropped > 10 and abs(st.samples_lost - dropped) <= 3
    assert sum(np.diff([s.seq for s in r.received]) - 1) == st.samples_lost
    assert st.frames_corrupt == 0
    assert any(re.fullmatch(r"serial link: \d+ samples? lost \(sequence gaps\) in the last second", e)
               for e in r.events)


def test_watchdog_centres_the_valve_within_100_ms_of_the_last_command(servers, cyl_a):
    r = session(servers, cyl_a, 1.0, "--serial", "--watchdog-ms", "50", quiet_after=0.5)
    assert r.code == 0
    last_answered = max(r.replies)
    t_last = next(s.t for s in r.samples if s.seq == last_answered)
    # (a busy machine may have held the host up long enough for an earlier trip)
    tripped = next(s for s in r.samples if s.status & Status.WATCHDOG and s.seq > last_answered)
    assert 0.05 < tripped.t - t_last <= 0.1  # measured on the rig's clock
    after = [s for s in r.samples if s.seq >= tripped.seq]
    assert len(after) > 100 and all(s.u_applied == 0.0 and s.status & Status.WATCHDOG for s in after)
    assert any(re.fullmatch(r"rig reports watchdog: valve centred after 5\d ms of host silence", e)
               for e in r.events)
    assert r.rig.stats.rig_errors >= 1


def test_a_stall_delays_samples_without_losing_them(servers, cyl_a):
    r = session(servers, cyl_a, 2.0, "--serial", "--stall-at", "0.8", "--stall-for", "0.3")
    assert r.code == 0
    assert r.rig.stats.samples_lost == 0 and np.all(np.diff([s.seq for s in r.received]) == 1)
    assert "fault: link stalled for 0.3 s" in r.server.stderr()
    # the host saw nothing for the stall, so it sent nothing, so the rig's watchdog tripped
    assert any(s.status & Status.WATCHDOG for s in r.samples)


def test_a_vanished_rig_is_found_again_at_its_link(servers, cyl_a, tmp_path):
    link = str(tmp_path / "rig")
    first = servers("--serial", "--link", link, "--vanish-at", "1.0", name="first")
    assert os.readlink(link) == first.path
    events = []
    rig = SerialRig(link, on_event=events.append)
    state = {}

    def restart_when_lost(samples):
        if "lost" not in state and any("link lost" in e for e in events):
            state["lost"] = len(samples)
            assert first.proc.wait(timeout=10) == 0  # the rig vanished: its server ends by itself
            assert not os.path.lexists(link)
            state["second"] = servers("--serial", "--link", link, name="second")
        return "lost" in state and len(samples) > state["lost"] + 500

    samples, _ = closed_loop(rig, cyl_a, 15.0, until=restart_when_lost)
    rig.stop()
    assert "lost" in state, events
    assert os.readlink(link) == state["second"].path
    assert state["second"].stop() == 0
    lost = [e for e in events if "link lost" in e]
    assert len(lost) == 1 and re.fullmatch(rf"serial link lost \({re.escape(link)}: .+\); retrying", lost[0])
    back = [e for e in events if "link back" in e]
    assert len(back) == 1 and re.fullmatch(r"serial link back after \d+\.\d s; about \d+ samples lost", back[0])
    assert rig.stats.reconnects == 1 and len(samples) > state["lost"] + 500
    assert np.all(np.diff([s.t for s in samples]) > 0)  # the new rig's clock starts at 0; t does not


def test_a_rig_that_comes_back_reports_exactly_what_was_lost(servers, cyl_a, tmp_path):
    link = str(tmp_path / "rig")
    srv = servers("--serial", "--link", link, "--vanish-at", "0.8", "--vanish-for", "0.5")
    events = []
    rig = SerialRig(link, on_event=events.append)
    samples, _ = closed_loop(rig, cyl_a, 2.5)
    rig.stop()
    assert srv.proc.stdout.readline().strip() == os.readlink(link)  # the new pty, printed on stdout
    assert srv.stop() == 0
    assert not os.path.lexists(link)  # a server that ends takes its link along
    (back,) = [e for e in events if "link back" in e]
    lost = int(re.fullmatch(r"serial link back after \d+\.\d s; (\d+) samples lost", back).group(1))
    assert 400 < lost < 1500 and rig.stats.samples_lost == lost  # the rig ran on: sequence numbers tell


@pytest.mark.parametrize("argv, fragment", [
    (["--can", "--corrupt", "0.1"], "--corrupt applies to the serial transport only"),
    (["--serial", "--stall-at", "1"], "--stall-at and --stall-for go together"),
    (["--serial", "--rate", "5"], "--rate must lie between"),
    (["--serial", "--drop", "1.5"], "--drop is a probability"),
    (["--serial", "--link", "/nonexistent/dir/rig"], "--link /nonexistent/dir/rig: the folder /nonexistent/dir "
                                                      "does not exist"),
    (["--serial", "--vanish-for", "1"], "--vanish-for needs --vanish-at"),
    (["--serial", "--jitter-us", "500"], "--jitter-us must lie between 0 and a quarter period (250 us)"),
    (["--serial", "--effect", "nonsense"], "unknown effect"),
])
def test_virtual_rig_refuses_bad_options(capsys, argv, fragment):
    code = main(["virtual-rig", "--config", str(CFG), *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and fragment in err[0], err
