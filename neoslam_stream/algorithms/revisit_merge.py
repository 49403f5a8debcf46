"""Stage D on a route driven again and again: a revisit is merged into the place it matched.

The calibrated decision (calibration.py) accepts a closure only after evidence over ``sequence_m``
of travel, so the first frames of every revisit stretch are refused. In the paper's rule each such
frame that opens an interval (Y_k, its union of winner-cell SDRs y_t) makes a new template, and a
route driven many times gains about one template per refused interval on every lap: 70-74 a lap on
the default route, 136 of 142 of them on frames that stood out on their own (confidence >= 0) and
were refused only because the stretch had not yet confirmed them (studies/long_runs.py). Each
becomes a new view for the pose cells, hence a new experience, and an interval in D's index.

With ``spatial_view.merge_revisits`` (docs/long_runs.md):

* **hold**: a new interval whose frame stands out on its own (confidence >= 0) takes the template
  the robot already had instead of a new one, for at most one stretch of evidence (L frames,
  ``RunCalibration.sequence_frames``); the pose cells see the place they were at, not a new view;
* **merge**: when a closure then confirms the stretch, each interval registered within it (held, or
  a refused frame's new template) is the place its frame matched (``_confirm_duplicates``), and it
  never enters D's index: the place is there already, from its first visit, with its own union and
  descriptor row;
* **expire**: a held interval that no closure confirmed within its stretch was a view of the place
  the robot had just been at: the first such one of a place enters the index as that place's
  second view (under the held template, the one its frames were sent with), later ones are
  dropped (a template of its own would be a second place where there is one, and the two would
  compete on every later visit, as the references of their frames would disagree);
* **forget**: an interval that does not enter the index (a revisit whose every frame closed, or
  one merged) is dropped from D's per-interval stores once it is no longer the view a moment ago.

Decisions wait for the stretch, so the intervals that closed are indexed in order once no closure
can confirm them any more (:meth:`RevisitMerge.settle`), and always before they could be a
candidate (one shortest loop at twice the speed, far longer than a stretch; ``force``). What D
keeps then grows with the places, not with the laps. No constant is involved: the stretch is the
decision's own.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

#: a decision on a closed interval: into the index, or dropped (its frames were a known place;
#: EXPIRE: a held interval that no closure confirmed)
INDEX, EXPIRE, DROP = "index", "expire", "drop"


class RevisitMerge:
    """The intervals that closed and wait for their stretch's verdict, and what is known of them."""

    def __init__(self) -> None:
        #: closed intervals not yet indexed or dropped, in order
        self.waiting: deque[int] = deque()
        #: of each waiting interval: whether every frame of it closed onto an older place
        self.all_closed: dict[int, bool] = {}
        #: interval -> the frame its template was made or held on (a closure within L frames confirms it)
        self.registered: dict[int, int] = {}
        #: intervals that took the current template (hold) and were not confirmed yet
        self.held: set[int] = set()
        #: intervals confirmed as an older place: never indexed
        self.merged: set[int] = set()
        #: the places (templates) that took an expired hold as their second view
        self.second_views: set[int] = set()
        #: the first frame of the current run of held frames (-1: none)
        self.hold_from = -1
        #: dropped intervals whose stores are kept while they are the newest but one
        self.dropped: deque[int] = deque()
        #: what the run did: intervals held, merged, expired (held but a new place), dropped
        self.counts = {"held": 0, "merged": 0, "expired": 0, "dropped": 0}

    def may_hold(self, t: int, confidence: float, stretch: int) -> bool:
        """Whether frame t, which opens an interval and closed no loop, keeps the current template:
        it stood out on its own, and the run of held frames is at most one stretch long."""
        if confidence < 0 or (self.hold_from >= 0 and t - self.hold_from > stretch):
            return False
        if self.hold_from < 0:
            self.hold_from = t
        return True

    def end_hold(self) -> None:
        """A frame closed a loop or made a template: the run of held frames is over."""
        self.hold_from = -1

    def register(self, k: int, t: int, held: bool) -> None:
        """Interval k's template was made (or held, ``held``) on frame t while its frame matched a place."""
        self.registered[k] = t
        if held:
            self.held.add(k)
            self.counts["held"] += 1

    def confirm(self, k: int) -> None:
        """A closure confirmed interval k as the place its frame matched."""
        if k in self.registered:
            self.merged.add(k)
            self.held.discard(k)
            self.counts["merged"] += 1

    def second_view(self, template: int) -> bool:
        """Whether an expired hold of ``template`` enters the index as that place's second view
        (once per place; later ones are dropped)."""
        if template in self.second_views:
            return False
        self.second_views.add(template)
        return True

    def close(self, k: int, all_closed: bool) -> None:
        self.waiting.append(k)
        self.all_closed[k] = all_closed

    def settle(self, t: int, stretch: int, force: Callable[[int], bool] | None = None) -> list[tuple[int, str]]:
        """After frame t: the waiting intervals, in order, that no closure can confirm any more
        (registered more than ``stretch`` frames ago, or never), or that ``force`` says must be
        decided now, with their decision (INDEX, EXPIRE, DROP)."""
        out = []
        while self.waiting:
            k = self.waiting[0]
            drop = k in self.merged or self.all_closed[k]
            if not drop and self.registered.get(k, -stretch - 1) + stretch > t and not (force and force(k)):
                break
            self.waiting.popleft()
            decision = DROP if drop else EXPIRE if k in self.held else INDEX
            self.counts["dropped"] += decision == DROP
            self.counts["expired"] += decision == EXPIRE
            for d in (self.all_closed, self.registered):
                d.pop(k, None)
            self.held.discard(k)
            self.merged.discard(k)
            out.append((k, decision))
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"waiting": [[k, int(self.all_closed[k])] for k in self.waiting],
                "registered": [[k, f] for k, f in self.registered.items()], "held": sorted(self.held),
                "merged": sorted(self.merged), "hold_from": self.hold_from, "dropped": list(self.dropped),
                "second_views": sorted(self.second_views), "counts": dict(self.counts)}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.waiting = deque(int(k) for k, _ in st["waiting"])
        self.all_closed = {int(k): bool(c) for k, c in st["waiting"]}
        self.registered = {int(k): int(f) for k, f in st["registered"]}
        self.held = {int(k) for k in st["held"]}
        self.merged = {int(k) for k in st["merged"]}
        self.hold_from = int(st["hold_from"])
        self.dropped = deque(int(k) for k in st["dropped"])
        self.second_views = {int(t) for t in st["second_views"]}
        self.counts = {k: int(v) for k, v in st["counts"].items()}


class Stored:
    """A per-interval store (index k = 0, 1, ...) that may forget entries: D's lists when revisits
    merge, holding the places and the recent intervals only. Reads of a forgotten k raise KeyError."""

    def __init__(self, items: dict[int, Any] | None = None, n: int = 0) -> None:
        self._d: dict[int, Any] = dict(items or {})
        self._n = n

    def append(self, v: Any) -> None:
        self._d[self._n] = v
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def _key(self, k: int) -> int:
        return k + self._n if k < 0 else k

    def __getitem__(self, k: int) -> Any:
        return self._d[self._key(k)]

    def __setitem__(self, k: int, v: Any) -> None:
        k = self._key(k)
        if k not in self._d:
            raise KeyError(k)
        self._d[k] = v

    def __contains__(self, k: int) -> bool:
        return self._key(k) in self._d

    def forget(self, k: int) -> None:
        self._d.pop(k, None)

    def keys(self) -> list[int]:
        return sorted(self._d)

    def stored(self) -> int:
        return len(self._d)
