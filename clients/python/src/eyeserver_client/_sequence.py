"""Keeping a stream's place by ``seq`` across reconnections (both clients' streams).

The daemon numbers the messages of each stream (``seq``, increasing by one). The event stream
replays what a reconnecting client missed (``?after=seq``) as long as the daemon keeps it (its
newest 1024 events); the pose stream does not (a pose that went by is no use to a beam hold).
So a stream resumes by replay where it can and by *accounting* beyond that. On ``/ws/events``
the first message of a connection, the ``hello``, says where it starts (``last_seq``: where the
replay begins); on ``/ws/pose`` the first numbered message does. Against the last ``seq`` the
client had, that tells how many went by and are lost
(:class:`~eyeserver_client.messages.Resumed` ``missed``), or that the daemon started anew (its
``seq`` then starts again from 1: ``restarted``). A message whose ``seq`` the client already
had is never passed on twice.
"""

from __future__ import annotations

from eyeserver_client.messages import Disconnected, Event, Hello, Message, Resumed

__all__ = ["Sequence"]


class Sequence:
    """The place of one stream: the last ``seq`` passed on, and whether a loss is pending."""

    def __init__(self) -> None:
        self.last_seq: int | None = None
        self._resuming = False

    def lost(self, reason: str) -> Disconnected:
        """The notice for a lost connection; the next connection's start is checked."""
        self._resuming = True
        return Disconnected(reason=reason, last_seq=self.last_seq)

    def receive(self, message: Message) -> list[Message]:
        """What to pass on for ``message``: nothing (a repeat), the message, or a
        :class:`Resumed` notice and the message."""
        if isinstance(message, Hello):
            out: list[Message] = []
            if self._resuming:
                out.append(self._resumed(message.last_seq))
            self.last_seq = message.last_seq
            return [*out, message]
        if not isinstance(message, Event):  # heartbeats and notices have no seq
            return [message]
        out = []
        if self._resuming:
            out.append(self._resumed(message.seq - 1))
        elif self.last_seq is not None and message.seq <= self.last_seq:
            return []  # already passed on (a daemon that replays): never twice
        self.last_seq = message.seq
        return [*out, message]

    def _resumed(self, before_first: int) -> Resumed:
        """``before_first``: the ``seq`` just before the first message of the new connection."""
        self._resuming = False
        previous = self.last_seq
        if previous is None:  # nothing numbered came before the loss
            return Resumed(last_seq=None, missed=None)
        if before_first < previous:
            return Resumed(last_seq=previous, missed=None, restarted=True)
        return Resumed(last_seq=previous, missed=before_first - previous)
