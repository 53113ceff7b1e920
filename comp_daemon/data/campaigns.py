"""Reading any measurement campaign: a tracker data set, a ballbar or a cross-bar campaign.

:func:`read_campaign` reads the table once (every column kept), tells the form by its columns
(:func:`comp_daemon.data.bars.campaign_kind`) and checks it by that form's rules.
"""

from __future__ import annotations

import os
from typing import Literal

from numpy.typing import ArrayLike

from comp_daemon.data.ballbar import BallbarCampaign, TcpFunction, ballbar_from_dataset
from comp_daemon.data.bars import CampaignKind, campaign_kind, read_table
from comp_daemon.data.crossbar import CrossbarCampaign, crossbar_from_dataset
from comp_daemon.data.options import ReadOptions
from comp_daemon.data.table import Dataset

__all__ = ["Campaign", "campaign_of", "read_campaign"]

Campaign = BallbarCampaign | CrossbarCampaign


def campaign_of(
    table: Dataset, *, tcp_mm: TcpFunction | None = None, expect: CampaignKind | None = None
) -> Campaign | None:
    """The ballbar or cross-bar campaign of ``table`` (read with every column kept), ``None`` for a
    table of neither form; ``expect`` refuses the other form."""
    kind = campaign_kind(table)
    if expect is not None and kind != expect:
        found = "a tracker data set" if kind is None else f"a {kind} campaign"
        raise ValueError(f"{table.source}: {found}, not a {expect} campaign")
    if kind == "ballbar":
        return ballbar_from_dataset(table, tcp_mm=tcp_mm)
    if kind == "crossbar":
        return crossbar_from_dataset(table)
    return None


def read_campaign(
    path_or_data: str | os.PathLike[str] | bytes | bytearray,
    *,
    fmt: Literal["csv", "json"] | None = None,
    source: str | None = None,
    limits_deg: ArrayLike | None = None,
    options: ReadOptions | None = None,
    tcp_mm: TcpFunction | None = None,
    expect: CampaignKind | None = None,
) -> Campaign:
    """A ballbar or cross-bar campaign from a file (CSV, or JSON records); a tracker data set is refused."""
    table = read_table(path_or_data, fmt=fmt, source=source, limits_deg=limits_deg, options=options)
    campaign = campaign_of(table, tcp_mm=tcp_mm, expect=expect)
    if campaign is None:
        raise ValueError(
            f"{table.source}: neither a ballbar campaign (bar_mm, cx, cy, cz, arc) nor a cross-bar campaign "
            "(placement, socket, bar_l_mm)"
        )
    return campaign
