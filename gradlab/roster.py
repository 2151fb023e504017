"""The members of one trainer, built once (:class:`Roster`): each config resolved once, the members checked once
for what they must share, and ordered once, as the trainer trains them.

The one place that turns configs into members: ``ablate`` builds it before any folder is made (so that a refusal
costs nothing) and hands it to the trainer, which then neither resolves, checks nor sorts again; a caller that
gives the trainer configs gets it built there. A run alone is a roster of one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

from gradlab.config import SHACConfig, resolve_config
from gradlab.members import check_population, render_order

__all__ = ["Roster"]

T = TypeVar("T")


@dataclass(frozen=True)
class Roster:
    """The resolved configs of a trainer's members, in the order it trains them.

    ``cfgs[k]``: member ``k``'s config, every preset value filled in; ``order[k]``: its index among the configs
    :meth:`of` was given. The order is :func:`gradlab.members.render_order`'s (members of one image model
    adjacent, so that they render in one call); the batched kernels' sums run over the members in this order,
    so it is part of a population's arithmetic.
    """

    cfgs: tuple[SHACConfig, ...]
    order: tuple[int, ...]

    @classmethod
    def of(cls, cfgs: Sequence[SHACConfig]) -> Roster:
        """The roster of ``cfgs`` (a run alone: a list of one); ValueError naming the flag for configs that are
        not valid or cannot train as one trainer's members (:func:`gradlab.members.check_population`)."""
        if isinstance(cfgs, SHACConfig) or not all(isinstance(c, SHACConfig) for c in cfgs):
            raise TypeError(f"a trainer's members are a list of SHACConfig (a run alone: a list of one), got "
                            f"{type(cfgs).__name__}")
        resolved = [resolve_config(c) for c in cfgs]
        check_population(resolved)
        order = tuple(sorted(range(len(resolved)), key=lambda i: render_order(resolved[i])))
        return cls(tuple(resolved[i] for i in order), order)

    def __len__(self) -> int:
        return len(self.cfgs)

    @property
    def shared(self) -> SHACConfig:
        """A config holding the settings every member shares (those outside ``vocabulary.MEMBER_FIELDS``): the
        first member's; its member settings are that member's own."""
        return self.cfgs[0]

    def arrange(self, items: Sequence[T]) -> list[T]:
        """``items`` given in the order of the configs :meth:`of` took, in the members' order."""
        if len(items) != len(self.order):
            raise ValueError(f"{len(items)} items for {len(self.order)} members")
        return [items[i] for i in self.order]
