"""Geometric V2X radio model: propagation, obstacles, PHY, medium access, congestion control, CPM rules.

Pure and numpy-vectorised; :class:`~.link.RadioChannel` puts them behind the
:class:`~mapcontainer.channel.Channel` interface for the pipeline and the channel relay.
"""

from .link import RADIO_CAUSES, RadioChannel, RadioParams, RadioProfile, make_channel

__all__ = ["RADIO_CAUSES", "RadioChannel", "RadioParams", "RadioProfile", "make_channel"]
