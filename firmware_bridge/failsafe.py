"""The bridge's failsafe as a clock-driven decision, without I/O.

`CommandGate` answers two questions: may this fresh command go to the vehicle now, and is a
stop due now. Its rules are the failsafe:

- a command goes out once, when it arrives, and only while the link is up; nothing is ever
  sent again later, so an old command cannot be replayed;
- when no command has arrived for `timeout_s` (or none since the link came up), a stop is due,
  and again every `stop_period_s` until a fresh command arrives;
- while the link is down, stops keep being due (a link that lost only its downlink may still
  hear them), and coming back up counts as "no command yet": motion resumes only with a
  command that arrives after that;
- once closed (shutdown), no command goes out any more.

The daemon calls it under one lock with the send, so what goes on the wire is in decision order.
"""

from __future__ import annotations

import math


class CommandGate:
    """Decides between forwarding a fresh command and sending stop."""

    def __init__(self, timeout_s: float, stop_period_s: float) -> None:
        self.timeout_s = timeout_s
        self.stop_period_s = stop_period_s
        self.link_up = False
        self.closed = False
        self._last_command_s = -math.inf
        self._last_stop_s = -math.inf

    def accept_command(self, now_s: float) -> bool:
        """A fresh command arrived at `now_s`: True if it may be sent now (then send it)."""
        if self.closed or not self.link_up:
            return False
        self._last_command_s = now_s
        return True

    def set_link(self, up: bool) -> None:
        """The vehicle link came up or went down; either way, motion needs a fresh command."""
        if up != self.link_up:
            self._last_command_s = -math.inf
        self.link_up = up

    def close(self) -> None:
        """Refuse every later command (the bridge is shutting down)."""
        self.closed = True

    def driving(self, now_s: float) -> bool:
        """True while the last command is fresh (the vehicle may be moving on it)."""
        return self.link_up and not self.closed and now_s - self._last_command_s < self.timeout_s

    @property
    def was_driving(self) -> bool:
        """True when a command went out after the last stop (the car may be moving)."""
        return self._last_command_s > self._last_stop_s

    def stop_due(self, now_s: float) -> bool:
        """True when a stop must be sent now (then send it and call `stop_sent`)."""
        if self.driving(now_s):
            return False
        return now_s - self._last_stop_s >= self.stop_period_s or (
            self._last_stop_s < self._last_command_s + self.timeout_s <= now_s
        )

    def stop_sent(self, now_s: float) -> None:
        """Record that a stop went out at `now_s`."""
        self._last_stop_s = now_s

    def next_check_s(self, now_s: float) -> float:
        """The earliest time `stop_due` can turn true without a new event."""
        if self.driving(now_s):
            return self._last_command_s + self.timeout_s
        return max(now_s, self._last_stop_s + self.stop_period_s)
