"""Time jumps: a reset or a restored snapshot moves sim time; handlers hear about it."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from evclock._errors import InvalidArgumentError
from evclock.time._time import Duration, Time


@dataclasses.dataclass(frozen=True, slots=True)
class TimeJump:
    """A discontinuity of the clock: ``after - before`` is the ``delta`` (negative: backwards)."""

    before: Time
    after: Time

    @property
    def delta(self) -> Duration:
        """Signed size of the jump."""
        return self.after - self.before


_ONE_NS = Duration(nanoseconds=1)


@dataclasses.dataclass(frozen=True, slots=True)
class JumpThreshold:
    """Which jumps a handler wants, like rcl's ``rcl_jump_threshold_t``.

    ``min_forward``: forward jumps at least this large (None: never called for forward jumps).
    ``min_backward``: backward jumps at least this large in magnitude (None: never).
    Defaults: every backward jump, and no forward jump - so ``JumpThreshold(min_forward=d)``
    still reports every backward jump; pass ``min_backward=None`` to hear forward jumps only.
    """

    min_forward: Duration | None = None
    min_backward: Duration | None = _ONE_NS

    def __post_init__(self) -> None:
        for name in ("min_forward", "min_backward"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, Duration) or value.nanoseconds <= 0):
                raise InvalidArgumentError(
                    f"JumpThreshold.{name} must be a positive Duration or None, got {value!r}"
                )

    def matches(self, jump: TimeJump) -> bool:
        """Whether ``jump`` is large enough to report."""
        delta = jump.delta.nanoseconds
        if delta > 0:
            return self.min_forward is not None and delta >= self.min_forward.nanoseconds
        if delta < 0:
            return self.min_backward is not None and -delta >= self.min_backward.nanoseconds
        return False


JumpCallback = Callable[[TimeJump], object]


class JumpHandle:
    """A registered pair of jump callbacks; ``remove()`` unregisters them.

    Made by :meth:`Clock.on_jump`, not directly.

    :param registry: the clock's list of handles this one is registered in.
    :param pre: called with the :class:`TimeJump` before the clock jumps, or None.
    :param post: called with the :class:`TimeJump` after the clock jumped, or None.
    :param threshold: the :class:`JumpThreshold` a jump must pass to trigger the callbacks.
    """

    def __init__(
        self,
        registry: list[JumpHandle],
        pre: JumpCallback | None,
        post: JumpCallback | None,
        threshold: JumpThreshold,
    ) -> None:
        self._registry = registry
        self.pre = pre
        self.post = post
        self.threshold = threshold

    def remove(self) -> None:
        """Stop receiving jump callbacks (idempotent)."""
        if self in self._registry:
            self._registry.remove(self)
