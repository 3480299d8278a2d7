"""An Xsens MTi on a pseudo-terminal: answers Xbus configuration, streams MTData2 from a recording, injects faults.

Open :attr:`XsensSimulator.path` with any serial library (it is a real tty). Faults (:class:`FaultConfig`) corrupt
whole messages on the wire (bit flips, dropped bytes, garbage between messages) and every corrupted message is
recorded by its PacketCounter, so a test can check that exactly the intact ones come out of a parser.
:meth:`unplug` closes the pty, as pulling the USB cable does.

One world: with ``trial_clock`` (a :class:`drivers.trial_clock.TrialClock` shared with the other simulators of a
session) the device samples on the trial's grid: entering Measurement at wall time t it measures first the trial's
first sample at or after t (modulo the trial's length when looping), at that sample's instant, as a physical tracker
samples the one world; without one every entry into Measurement plays the trial on from where the previous one
stopped (sample 0 at first). The device's own clock and
counters stay its own: PacketCounter counts its messages, SampleTimeFine (with a trial clock) counts 10 kHz ticks
from its power-up (:meth:`start`). ``latency_s`` delays every message: measured at t, its bytes leave at t + latency.
"""

from __future__ import annotations

import fcntl
import math
import os
import select
import sys
import termios
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from drivers.trial_clock import TrialClock
from drivers.xsens import frames, xbus
from drivers.xsens.source import ImuSource
from msk_core.errors import ConfigError, ProtocolError

DEFAULT_DEVICE_ID = 0x03700ABC  # 037xxxxx: an MTi-G-700-series device id
DEFAULT_PRODUCT_CODE = "MTi-G-710-2A8G4"
DEFAULT_FIRMWARE = (1, 8, 2)
#: Factory default: quaternion at 100 Hz plus packet counter.
FACTORY_OUTPUTS = [xbus.OutputSetting(0x1020, 0xFFFF), xbus.OutputSetting(0x2010, 100)]
#: Outputs an MTi-G-710 accepts that the simulator has no values for (GNSS PVT data, satellite info): accepted and
#: echoed like a real device, then omitted from MTData2 as a device without GNSS reception would.
ACCEPTED_WITHOUT_DATA = frozenset({0x7010, 0x7020})
DEFAULT_BAUDRATE = 115200


@dataclass(frozen=True)
class FaultConfig:
    """Per-message fault probabilities (at most one fault per message) and an optional unplug."""

    bit_flip: float = 0.0
    drop_byte: float = 0.0
    garbage: float = 0.0  # random bytes (with preambles) inserted before the message; the message stays intact
    unplug_after_messages: int | None = None
    seed: int = 0


@dataclass
class SimulatorStats:
    messages_sent: int = 0
    corrupted_counters: list[int] = field(default_factory=list)  # PacketCounter of every corrupted MTData2
    garbage_inserts: int = 0
    bytes_dropped: int = 0  # written while no host was reading (line buffer full)
    commands: int = 0
    latency_s: float = 0.0  # the stated device latency applied to every message (XsensSimulator latency_s)
    start_index: int | None = None  # source sample the latest entry into Measurement measured first (None: none yet)
    samples_skipped: int = 0  # with a trial clock: samples not sent because the simulator fell > 0.5 s behind


class XsensSimulator:
    """``with XsensSimulator(source) as sim: open(sim.path)``; starts in Config state after a WakeUp handshake
    window of 500 ms like a real MTi (no WakeUpAck -> Measurement with the current outputs)."""

    def __init__(
        self,
        source: ImuSource,
        *,
        device_id: int = DEFAULT_DEVICE_ID,
        product_code: str = DEFAULT_PRODUCT_CODE,
        firmware: tuple[int, int, int] = DEFAULT_FIRMWARE,
        faults: FaultConfig | None = None,
        speed: float = 1.0,
        loop: bool = True,
        wakeup_window_s: float = 0.5,
        trial_clock: TrialClock | None = None,
        latency_s: float = 0.0,
        measure_not_before: Callable[[], float | None] | None = None,
        stable_link: str | os.PathLike[str] | None = None,
        unsupported_outputs: frozenset[int] = frozenset(),
        error_replies: dict[int, int] | None = None,
    ) -> None:
        """``trial_clock``: the one world a session's simulators sample (None: each entry into Measurement continues
        the trial from where it stopped); ``latency_s``: device seconds between measuring a sample and its bytes
        leaving; ``measure_not_before``: the earliest wall instant (``time.monotonic()``) the tracker measures from
        after entering Measurement, None while it is not known yet (it waits): a tracker switched on after another
        device, e.g. a given time after the Trigno starts; ``stable_link``: a path that names this tracker while it
        is plugged in, as udev's ``/dev/serial/by-id`` link does: created at :meth:`start`, removed at
        :meth:`unplug` and :meth:`close`. A host reconnecting through it finds nothing while the tracker is away,
        even when the freed pseudo-terminal goes to another device meanwhile. ``unsupported_outputs``: data ids this
        device does not apply, left out of what it acknowledges and sends (0x1060: a device without SampleTimeFine);
        ``error_replies``: message id -> the Error code this device answers it with (a request it does not support)."""
        if not (math.isfinite(speed) and speed > 0):
            raise ConfigError("must be a positive number", field="speed", value=speed)
        if not (math.isfinite(latency_s) and latency_s >= 0):
            raise ConfigError(
                "device latency must be a finite number of seconds >= 0", field="latency_s", value=latency_s
            )
        self.source = source
        self.device_id = device_id
        self.product_code = product_code
        self.firmware = firmware
        self.faults = faults or FaultConfig()
        self.speed = speed
        self.loop = loop
        self.wakeup_window_s = wakeup_window_s
        self.trial_clock = trial_clock
        self.latency_s = latency_s
        self.measure_not_before = measure_not_before
        self._first_pending = False  # in Measurement, waiting for measure_not_before to say when it starts
        self.stats = SimulatorStats(latency_s=latency_s)
        self.baudrate = DEFAULT_BAUDRATE
        self.path = ""
        self.stable_link = os.fspath(stable_link) if stable_link is not None else None
        self.unsupported_outputs = frozenset(unsupported_outputs)
        self.error_replies = dict(error_replies or {})
        self._linked = False  # stable_link names this simulator's pty (until unplug/close)
        self.measuring = False
        self.unplugged = False
        self._held = False
        self._outputs = list(source.recorded_config) if source.raw_payloads else list(FACTORY_OUTPUTS)
        self._verbatim = bool(source.raw_payloads)  # replay recorded payloads until outputs are reconfigured
        self._rng = np.random.default_rng(self.faults.seed)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = -1
        self._slave = -1
        self._counter = 0
        self._sample = 0  # samples measured so far (without a trial clock: also the source index of the next)
        self._grid = 0  # with a trial clock: the next sample's index on the trial's grid at the output rate
        self._next_due = 0.0  # wall instant (time.monotonic) the next message leaves
        self._measured_at = 0.0  # with a trial clock: wall instant the next sample is measured
        self._powered_at = 0.0  # wall instant of power-up (start): SampleTimeFine's origin with a trial clock
        self._lock = threading.Lock()
        self._awaiting_ack = False
        self._wake_deadline = 0.0

    # ------------------------------------------------------------------------------------------ lifecycle
    def __enter__(self) -> XsensSimulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> XsensSimulator:
        if self._thread is not None:
            return self
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        tty.setraw(self._master)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        if self.stable_link is not None:
            try:
                self._link()
            except BaseException:
                self._close_fds()
                raise
        self._powered_at = time.monotonic()
        self._thread = threading.Thread(target=self._run, daemon=True, name="xsens-sim")
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._close_fds()

    def hold(self) -> None:
        """Stop sending measurements from now on while the port stays open: a clean end of a simulated session,
        after which ``stats.messages_sent`` is final and the host can read all of it."""
        self._held = True

    def unplug(self) -> None:
        """Close the pty like a pulled cable: the reader sees a hang-up / EIO."""
        self.unplugged = True
        self._stop.set()
        if self._thread is not None and threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)
        self._close_fds()

    def _link(self) -> None:
        """Name the pty by ``stable_link``, replacing a link left from before (atomically, as udev does)."""
        link = str(self.stable_link)
        if os.path.lexists(link) and not os.path.islink(link):
            raise ConfigError(
                "is not a symbolic link: the simulator replaces only a link", field="stable_link", value=link
            )
        staged = f"{link}.{os.getpid()}.{threading.get_ident()}"
        os.symlink(self.path, staged)
        try:
            os.replace(staged, link)
        except OSError:
            os.unlink(staged)
            raise
        self._linked = True

    def _close_fds(self) -> None:
        with self._lock:
            if self._linked:  # this simulator's name, not one a replugged successor on the same pty number made
                self._linked = False
                try:
                    if os.readlink(str(self.stable_link)) == self.path:
                        os.unlink(str(self.stable_link))  # the device is gone: so is its name
                except OSError:  # removed meanwhile
                    pass
            for fd in (self._master, self._slave):
                if fd >= 0:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
            self._master = self._slave = -1

    # ------------------------------------------------------------------------------------------ main loop
    def _write(self, data: bytes) -> None:
        """Write to the line; when nobody reads for a while the bytes are lost, as on a real UART."""
        view = memoryview(data)
        while view:
            try:
                written = os.write(self._master, view)
            except BlockingIOError:
                _, writable, _ = select.select([], [self._master], [], 0.2)
                if not writable:
                    self.stats.bytes_dropped += len(view)
                    return
                continue
            view = view[written:]

    def _run(self) -> None:
        parser = xbus.XbusParser()
        try:
            self._power_up()
            while not self._stop.is_set():
                if self.measuring and self._first_pending:
                    self._schedule_first()
                now = time.monotonic()
                if self._awaiting_ack and now >= self._wake_deadline:
                    self._awaiting_ack = False
                    self._enter_measurement()
                timeout = 0.01
                if self.measuring:
                    timeout = max(0.0, min(timeout, self._next_due - now))
                readable, _, _ = select.select([self._master], [], [], timeout)
                if readable:
                    chunk = os.read(self._master, 4096)
                    for message in parser.feed(chunk):
                        self._handle(message)
                if self.measuring and not self._held and time.monotonic() >= self._next_due:
                    if not self._send_sample():
                        self.measuring = False
                        continue
                    self._schedule_next()
                    limit = self.faults.unplug_after_messages
                    if limit is not None and self.stats.messages_sent >= limit:
                        self._wait_until_read(0.5)  # unplug after the host has the last message
                        self.unplug()
                        return
        except OSError:
            pass  # pty closed under us (unplug/close)

    def _wait_until_read(self, timeout: float) -> None:
        # The tty layer moves bytes to the reader's queue asynchronously: require an empty queue several times.
        deadline = time.monotonic() + timeout
        empty = 0
        while time.monotonic() < deadline and empty < 5:
            time.sleep(0.01)
            pending = fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0")
            empty = empty + 1 if int.from_bytes(pending, sys.byteorder) == 0 else 0

    def _power_up(self) -> None:
        """Send WakeUp; without a WakeUpAck within the window the device goes to Measurement."""
        self.measuring = False
        self._write(xbus.encode_message(xbus.Mid.WAKE_UP))
        self._wake_deadline = time.monotonic() + self.wakeup_window_s
        self._awaiting_ack = True

    def _enter_measurement(self) -> None:
        """Measure from now on: without a trial clock the first sample is now; with one, the trial's next grid
        instant (its sample of that instant)."""
        if self.measuring:
            return
        self.measuring = True
        self._schedule_first()

    def _schedule_first(self) -> None:
        """The first sample's instants after entering Measurement (not before ``measure_not_before``)."""
        now = time.monotonic()
        self._first_pending = False
        if self.measure_not_before is not None:
            earliest = self.measure_not_before()
            if earliest is None:
                self._first_pending, self._next_due = True, math.inf
                return
            now = max(now, earliest)
        if self.trial_clock is None:
            self._next_due = now + self.latency_s / self.speed
            self.stats.start_index = self._sample
            return
        self._grid = self.trial_clock.first_index(now, self._rate(), self.speed)
        self._measured_at = self.trial_clock.instant(self._grid, self._rate(), self.speed)
        self._next_due = self._measured_at + self.latency_s / self.speed
        self.stats.start_index = self._trial_index()

    def _period(self) -> float:
        """Wall seconds between two samples at the output rate."""
        return 1.0 / (self._rate() * self.speed)

    def _trial_index(self) -> int:
        """With a trial clock: the source sample (unwrapped) of the next grid instant, nearest in time when the
        output rate differs from the source's."""
        return int(round(self._grid * self.source.rate_hz / self._rate()))

    def _schedule_next(self) -> None:
        """After a message: the next one's instants. A simulator far behind (debugger, load) does not burst: without
        a trial clock it resumes from now; with one it skips to the present on the grid (the skipped samples are
        counted, and the PacketCounter jumps over them as for messages lost on the line)."""
        period = self._period()
        if self.trial_clock is None:
            self._next_due += period
            if time.monotonic() - self._next_due > 0.5:
                self._next_due = time.monotonic()
            return
        self._grid += 1
        latency = self.latency_s / self.speed
        behind = time.monotonic() - (self.trial_clock.instant(self._grid, self._rate(), self.speed) + latency)
        if behind > 0.5:
            skipped = int(behind / period)
            self._grid += skipped
            self._counter = (self._counter + skipped) & 0xFFFF
            self.stats.samples_skipped += skipped
        self._measured_at = self.trial_clock.instant(self._grid, self._rate(), self.speed)
        self._next_due = self._measured_at + latency

    def _rate(self) -> float:
        rate = xbus.message_rate_hz(self._outputs)
        return self.source.rate_hz if self._verbatim or rate is None else rate

    # ------------------------------------------------------------------------------------------ commands
    def _reply(self, mid: int, data: bytes = b"") -> None:
        self._write(xbus.encode_message(mid, data))

    def _error(self, code: int) -> None:
        self._reply(xbus.Mid.ERROR, bytes((code,)))

    def _handle(self, message: xbus.XbusMessage) -> None:
        self.stats.commands += 1
        mid, data = message.mid, message.data
        if self._awaiting_ack:
            self._awaiting_ack = False  # WakeUpAck (or any command) inside the window: stay in Config
        if mid in self.error_replies:
            self._error(self.error_replies[mid])
        elif mid == xbus.Mid.GO_TO_CONFIG:
            self.measuring = False
            self._reply(xbus.Mid.GO_TO_CONFIG_ACK)
        elif mid == xbus.Mid.GO_TO_MEASUREMENT:
            self._reply(xbus.Mid.GO_TO_MEASUREMENT_ACK)
            self._enter_measurement()
        elif mid == xbus.Mid.REQ_DID:
            self._reply(xbus.Mid.DEVICE_ID, self.device_id.to_bytes(4, "big"))
        elif mid == xbus.Mid.REQ_PRODUCT_CODE:
            self._reply(xbus.Mid.PRODUCT_CODE, self.product_code.encode("ascii"))
        elif mid == xbus.Mid.REQ_FW_REV:
            self._reply(xbus.Mid.FIRMWARE_REV, bytes(self.firmware))
        elif mid == xbus.Mid.SET_OUTPUT_CONFIGURATION:
            if self.measuring:
                self._error(0x04)
            elif not data:
                self._reply(xbus.Mid.OUTPUT_CONFIGURATION, xbus.encode_output_configuration(self._outputs))
            else:
                self._set_outputs(data)
        elif mid == xbus.Mid.RESET:
            self._reply(xbus.Mid.RESET_ACK)
            self._power_up()
        elif mid == xbus.Mid.BAUDRATE:
            if data:  # SetBaudrate: takes effect after a reset; a pty has no line rate to change
                if len(data) != 1 or data[0] not in xbus.BAUD_CODES:
                    self._error(0x20)
                    return
                self.baudrate = xbus.BAUD_CODES[data[0]]
                self._reply(xbus.Mid.BAUDRATE_ACK)
            else:
                self._reply(xbus.Mid.BAUDRATE_ACK, bytes((xbus.baud_code(self.baudrate),)))
        elif mid == xbus.Mid.WAKE_UP_ACK:
            pass
        else:
            self._error(0x04)

    def _set_outputs(self, data: bytes) -> None:
        try:
            settings = xbus.decode_output_configuration(data)
        except ProtocolError:  # malformed SetOutputConfiguration payload: the device answers "invalid parameter"
            self._error(0x21)
            return
        for setting in settings:
            known = (
                xbus.RAW_QUANTITIES.get(setting.data_id)
                or xbus.FLOAT_QUANTITIES.get(setting.data_id & 0xFFF0)
                or setting.data_id in ACCEPTED_WITHOUT_DATA
            )
            if not known or (setting.frequency not in xbus.EVERY_MESSAGE and not 1 <= setting.frequency <= 2000):
                self._error(0x21)
                return
        settings = [s for s in settings if s.data_id not in self.unsupported_outputs]  # the ack says what was applied
        self._outputs = settings
        self._verbatim = False
        self._reply(xbus.Mid.OUTPUT_CONFIGURATION, xbus.encode_output_configuration(settings))

    # ------------------------------------------------------------------------------------------ streaming
    def _send_sample(self) -> bool:
        payload = self._next_payload()
        if payload is None:
            return False
        frame = xbus.encode_message(xbus.Mid.MT_DATA2, payload)
        counter = xbus.decode_mtdata2(payload).first("packet_counter")
        self._write(self._inject(frame, counter))
        self.stats.messages_sent += 1
        return True

    def _sample_time(self, absolute: int) -> tuple[int, int]:
        """(SampleTimeFine: 10 kHz ticks wrapping daily, SampleTimeCoarse: whole seconds) of the sample being sent:
        with a trial clock the device's own clock from power-up at the sample's instant; without one, the time of
        source sample ``absolute`` from sample 0."""
        if self.trial_clock is None:
            return int(round(absolute * 1e4 / self._rate())) % 864_000_000, int(absolute / self._rate())
        seconds = (self._measured_at - self._powered_at) * self.speed
        return int(round(seconds * 1e4)) % 864_000_000, int(seconds)

    def _next_payload(self) -> bytes | None:
        n = self.source.n_samples
        absolute = self._sample if self.trial_clock is None else self._trial_index()
        if n == 0 or (not self.loop and absolute >= n):
            return None
        k = absolute % n
        self._sample += 1
        if self._verbatim:
            return self.source.raw_payloads[k]
        items: list[tuple[int, object]] = []
        for setting in self._outputs:
            data_id = setting.data_id
            if data_id == 0x1020:
                items.append((data_id, (self._counter,)))
            elif data_id == 0x1060:
                items.append((data_id, (self._sample_time(absolute)[0],)))
            elif data_id == 0x1070:
                items.append((data_id, (self._sample_time(absolute)[1],)))
            elif data_id in (0xE010, 0xE020):
                items.append((data_id, (0,)))
            else:
                spec = xbus.FLOAT_QUANTITIES.get(data_id & 0xFFF0)
                array = self.source.arrays.get(spec[0]) if spec else None
                if spec is None or array is None:
                    continue  # the recording does not have it: the device would not output it either
                values = array[k]
                if spec[0] == "quaternion":
                    values = frames.from_enu(tuple(values), xbus.frame_of(data_id))
                items.append((data_id, tuple(values)))
        self._counter = (self._counter + 1) & 0xFFFF
        return xbus.encode_mtdata2(items)

    def _inject(self, frame: bytes, counter: int | None) -> bytes:
        faults = self.faults
        draw = self._rng.random()
        if draw < faults.bit_flip:
            data = bytearray(frame)
            position = int(self._rng.integers(0, len(data)))
            data[position] ^= 1 << int(self._rng.integers(0, 8))
            self._note_corrupted(counter)
            return bytes(data)
        draw -= faults.bit_flip
        if draw < faults.drop_byte:
            position = int(self._rng.integers(0, len(frame)))
            self._note_corrupted(counter)
            return frame[:position] + frame[position + 1 :]
        draw -= faults.drop_byte
        if draw < faults.garbage:
            size = int(self._rng.integers(1, 40))
            junk = self._rng.integers(0, 256, size, dtype=np.uint8)
            junk[self._rng.random(size) < 0.2] = xbus.PREAMBLE
            self.stats.garbage_inserts += 1
            return junk.tobytes() + frame
        return frame

    def _note_corrupted(self, counter: int | None) -> None:
        self.stats.corrupted_counters.append(-1 if counter is None else counter)
