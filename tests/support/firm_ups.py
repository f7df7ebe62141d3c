"""A stream session whose firm-ups of one stack wait for a gate: what the two connections' firm-up
queues (:mod:`service.api.stream`, :mod:`service.mrd.connection`) are tested with."""

from __future__ import annotations

import threading
from types import SimpleNamespace

from service.core.errors import InvalidParameter


class GatedSession:
    """``firm_up`` and ``end_stack`` of a stream session, recorded; the firm-up of ``held`` waits
    until :attr:`gate` is set; ending a stack not in ``stacks`` is refused."""

    def __init__(self, held: str, stacks: tuple[str, ...]) -> None:
        self.held, self.stacks = held, stacks
        self.gate, self.running = threading.Event(), threading.Event()
        self.calls: list[tuple[str, str]] = []

    def firm_up(self, stack: str) -> list:
        self.calls.append(("firm_up", stack))
        if stack == self.held:
            self.running.set()
            assert self.gate.wait(10), "the test never opened the gate"
        return []

    def end_stack(self, stack: str) -> SimpleNamespace:
        if stack not in self.stacks:
            raise InvalidParameter(f"stack: no open stack {stack!r}")
        self.calls.append(("end_stack", stack))
        return SimpleNamespace(updates=[], reacquire_of={})
