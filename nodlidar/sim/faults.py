"""Link fault injection for device emulators: lost and garbled bytes, delays, stalls,
disconnects. Reproducible: every random decision comes from one seeded generator.

Durations are in *simulated* seconds (the emulator's :class:`~nodlidar.sim.clock.SimClock`),
so a 2 s stall at clock rate 20 lasts 0.1 s of wall time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nodlidar.errors import require

__all__ = ["FaultConfig", "FaultAction", "FaultInjector"]


@dataclass(frozen=True)
class FaultConfig:
    """What goes wrong on the emulated link, and how often.

    Attributes
    ----------
    seed : int
        Seed of the fault generator.
    drop_byte_prob, corrupt_byte_prob : float
        Probability per transmitted byte of losing it / replacing it with a random byte.
    delay_prob : float
        Probability per message of holding it back ``delay_s`` [s, simulated] first.
    stall_prob : float
        Probability per message of the device hanging for ``stall_s`` [s, simulated]
        (no output, no input processed) before sending it.
    disconnect_prob : float
        Probability per message of the link going away instead of sending it; the
        device comes back (rebooted) after ``disconnect_s`` [s, simulated].
    stall_at, disconnect_at : tuple of int
        Message numbers (0-based, counting messages the fault layer saw) at which a
        stall / disconnect happens for sure - for deterministic tests.
    garble_at : tuple of int
        Message numbers in which one character gets its lowest bit flipped (still
        printable ASCII; its line's checksum catches it): the last content character of
        the first line after the status (before ``;<sum>`` on VV/PP/II lines, before the
        sum otherwise), or the status itself if the message has no such line.
    status_at : tuple of (int, str)
        ``(message number, status)``: that message is sent with this 2-character status
        instead of its own, with a matching sum - a device error status inside a stream
        (``"55"``), or a corruption the 6-bit sum cannot see (``"9y"`` has the sum of
        ``"99"``).
    scans_only : bool
        Apply the faults only to scan messages (GD/GS/MD/MS data), not to replies.
    skip_messages : int
        Leave the first ``skip_messages`` messages untouched (e.g. the handshake).
    """

    seed: int = 0
    drop_byte_prob: float = 0.0
    corrupt_byte_prob: float = 0.0
    delay_prob: float = 0.0
    delay_s: float = 0.0
    stall_prob: float = 0.0
    stall_s: float = 0.0
    disconnect_prob: float = 0.0
    disconnect_s: float = 0.0
    stall_at: tuple[int, ...] = ()
    disconnect_at: tuple[int, ...] = ()
    garble_at: tuple[int, ...] = ()
    status_at: tuple[tuple[int, str], ...] = ()
    scans_only: bool = False
    skip_messages: int = 0

    def __post_init__(self) -> None:
        for name in ("drop_byte_prob", "corrupt_byte_prob", "delay_prob", "stall_prob",
                     "disconnect_prob"):
            v = getattr(self, name)
            require(0.0 <= v <= 1.0, f"faults.{name}", v, "a probability in [0, 1]")
        for name in ("delay_s", "stall_s", "disconnect_s"):
            v = getattr(self, name)
            require(v >= 0.0, f"faults.{name}", v, ">= 0 s")
        require(self.skip_messages >= 0, "faults.skip_messages", self.skip_messages, ">= 0")
        for item in self.status_at:
            require(isinstance(item, tuple) and len(item) == 2 and isinstance(item[1], str)
                    and len(item[1]) == 2 and item[1].isascii(), "faults.status_at", item,
                    "(message number, 2 ASCII characters) pairs")

    @property
    def active(self) -> bool:
        """True if any fault can happen."""
        return any((self.drop_byte_prob, self.corrupt_byte_prob, self.delay_prob,
                    self.stall_prob, self.disconnect_prob, self.stall_at, self.disconnect_at,
                    self.garble_at, self.status_at))


@dataclass(frozen=True)
class FaultAction:
    """What to do with one outgoing message.

    Attributes
    ----------
    data : bytes
        Bytes to send (after drops/corruption); empty if disconnecting.
    wait_s : float
        Simulated seconds to wait before sending (delay + stall).
    stalled : bool
        The wait is a stall (device hung).
    disconnect_s : float or None
        If not None: drop the link now and come back after this many simulated seconds.
    dropped, corrupted : int
        Bytes lost / garbled in this message.
    """

    data: bytes
    wait_s: float = 0.0
    stalled: bool = False
    disconnect_s: float | None = None
    dropped: int = 0
    corrupted: int = 0


class FaultInjector:
    """Applies a :class:`FaultConfig` to a sequence of messages (not thread-safe)."""

    def __init__(self, config: FaultConfig | None = None):
        self.config = config or FaultConfig()
        self._rng = np.random.default_rng(self.config.seed)
        self.messages = 0

    def apply(self, message: bytes, is_scan: bool = False) -> FaultAction:
        """Decide the fate of one message."""
        cfg = self.config
        n = self.messages
        self.messages += 1
        if not cfg.active or n < cfg.skip_messages or (cfg.scans_only and not is_scan):
            return FaultAction(message)
        rng = self._rng
        if n in cfg.disconnect_at or (cfg.disconnect_prob and rng.random() < cfg.disconnect_prob):
            return FaultAction(b"", disconnect_s=cfg.disconnect_s)
        wait = 0.0
        stalled = False
        if n in cfg.stall_at or (cfg.stall_prob and rng.random() < cfg.stall_prob):
            wait += cfg.stall_s
            stalled = True
        if cfg.delay_prob and rng.random() < cfg.delay_prob:
            wait += cfg.delay_s
        data = message
        dropped = corrupted = 0
        if n in cfg.garble_at:
            data, hit = _garble_one(data)
            corrupted += hit
        for at, status in cfg.status_at:
            if at == n:
                data = _restatus(data, status)
        if cfg.corrupt_byte_prob or cfg.drop_byte_prob:
            a = np.frombuffer(data, dtype=np.uint8).copy()
            if cfg.corrupt_byte_prob:
                mask = rng.random(a.size) < cfg.corrupt_byte_prob
                n_hit = int(mask.sum())
                corrupted += n_hit
                if n_hit:
                    # add 1..255 so the byte surely changes
                    a[mask] = (a[mask].astype(np.int32) + rng.integers(1, 256, n_hit)) % 256
            if cfg.drop_byte_prob:
                keep = rng.random(a.size) >= cfg.drop_byte_prob
                dropped = int(a.size - keep.sum())
                a = a[keep]
            data = a.tobytes()
        return FaultAction(data, wait_s=wait, stalled=stalled, dropped=dropped,
                           corrupted=corrupted)


def _garble_one(message: bytes) -> tuple[bytes, int]:
    """Flip the lowest bit of one character (see ``FaultConfig.garble_at``)."""
    a = bytearray(message)
    echo_end = message.find(b"\n")
    status_end = message.find(b"\n", echo_end + 1)
    if echo_end < 0 or status_end < 0:
        return message, 0
    line_end = message.find(b"\n", status_end + 1)
    if line_end > status_end + 2:  # a line with content and a sum
        i = line_end - 2  # the last content character
        if a[i] == 0x3B and i > status_end + 1:  # ';' of a KEY:VALUE;S line
            i -= 1
    else:
        i = echo_end + 1  # the status
    a[i] ^= 0x01
    return bytes(a), 1


def _restatus(message: bytes, status: str) -> bytes:
    """``message`` with its status line replaced by ``status`` + its sum."""
    echo_end = message.find(b"\n")
    status_end = message.find(b"\n", echo_end + 1)
    if echo_end < 0 or status_end < 0:
        return message
    s = status.encode("ascii")
    line = s + bytes(((sum(s) & 0x3F) + 0x30,))
    return message[:echo_end + 1] + line + message[status_end:]
