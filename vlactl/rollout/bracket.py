"""The bracketing search on a reading shift that the box=action controller runs per re-plan: start small, grow until
the predicted quantity crosses its target, then false position inside the bracket (bisection where a saturating or
jumping response would make it hug an end). A push at an action-expert layer saturates the actions fast (dz goes
-0.8 -> +0.5 for a shift of 0.05 at expert.5), a gripper logit slowly, a decoded action token moves in jumps: no
derivative is trusted beyond the last two passes."""

from __future__ import annotations

MAX_SHIFT = 100.0  # the largest reading shift the search may ask for (reading units)
FIRST_GAIN = 0.1  # the first reading shift per action unit of the quantity's distance to the target


class Bracket:
    """One shift's search. `shift` is the next one to try; `update(miss)` takes the quantity's miss (quantity - target)
    at that shift and sets the next, returning False when there is nothing left to try (the largest shift allowed was
    tried and is still short)."""

    def __init__(self, origin: float, miss: float):
        """`origin`: the shift so far, where the quantity misses its target by `miss`."""
        self.origin, self.inner, self.outer = origin, (origin, miss), None  # (shift, miss) short of / past the target
        self.shift = origin - miss * FIRST_GAIN

    def update(self, miss: float) -> bool:
        shift, origin = self.shift, self.origin
        if (miss > 0) == (self.inner[1] > 0):  # still short of the target
            if shift == self.inner[0]:
                return False
            gain = (miss - self.inner[1]) / (shift - self.inner[0])
            self.inner = (shift, miss)
            if self.outer is None:  # extrapolate, at most 4x further (4x if it did not move towards the target)
                far = origin + 4 * (shift - origin)
                guess = shift - miss / gain if gain * miss < 0 else far
                guess = guess if abs(guess - origin) <= abs(far - origin) else far
                self.shift = max(-MAX_SHIFT, min(MAX_SHIFT, guess))
                return True
        else:
            self.outer = (shift, miss)
        (s0, m0), (s1, m1) = self.inner, self.outer
        guess = s0 - m0 * (s1 - s0) / (m1 - m0)
        width = abs(s1 - s0)
        self.shift = guess if min(s0, s1) + 0.1 * width < guess < max(s0, s1) - 0.1 * width else (s0 + s1) / 2
        return True
