"""Which topics of a ROS recording hold depth, colour and infrared: the choice and its CLI options.

Every command that opens recordings (`capture info/import`, `evaluate checkerboard/scan`,
`explain`) takes the same three options, declared once here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import typer


@dataclass(frozen=True)
class TopicChoice:
    """Topics named by the user (None: found automatically by the realsense-ros layouts).

    Travels with a recording's path to the workers that reopen it.
    """

    depth: str | None = None
    color: str | None = None
    infrared: str | None = None

    @property
    def given(self) -> bool:
        return any(t is not None for t in (self.depth, self.color, self.infrared))

    def to_dict(self) -> dict[str, str | None]:
        return {"depth": self.depth, "color": self.color, "infrared": self.infrared}


def topic_choice(depth: str | None = None, color: str | None = None,
                 infrared: str | None = None) -> TopicChoice | None:
    """The choice the three options make (None when none was given)."""
    choice = TopicChoice(depth, color, infrared)
    return choice if choice.given else None


_HELP = "ROS recordings: the {} image topic (default: found by the realsense-ros layout)."
DepthTopic = Annotated[str | None, typer.Option("--depth-topic", help=_HELP.format("depth"))]
ColorTopic = Annotated[str | None, typer.Option("--color-topic", help=_HELP.format("colour"))]
InfraredTopic = Annotated[str | None, typer.Option("--infrared-topic", help=_HELP.format("infrared"))]
