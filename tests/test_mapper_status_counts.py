"""A sender's cloud numbers never become a count the status cannot carry (found by `smana bench
fuzz`: clouds numbered 0, 2**63-1, 0, 2**63-1, ... made `clouds_lost_upstream` exceed uint64, and
every status and stats query failed from then on). In-process: handlers called without zenoh."""

from __future__ import annotations

import numpy as np

from smana.common.config import SmanaConfig
from smana.common.messages import SemanticCloud, ServiceStatus, decode, encode
from smana.services.mapper.service import MAX_SEQ_GAP, MapperService
from smana.services.mapper.takeover import build_map


class Sink:
    def put(self, msg):
        pass


def mapper() -> MapperService:
    svc = MapperService(SmanaConfig())
    svc.map = build_map(svc.config, svc.table)
    svc.delta_pub = Sink()
    return svc


def cloud(stamp: float, seq: int) -> SemanticCloud:
    return SemanticCloud(
        stamp_s=stamp,
        seq=seq,
        points=np.zeros((1, 3), "f4"),
        labels=np.ones(1, "u1"),
        confidences=np.ones(1, "f4"),
    )


def test_huge_jumps_in_cloud_numbers_keep_the_status_encodable():
    svc = mapper()
    for i, seq in enumerate([0, 2**63 - 1] * 4):
        svc.on_cloud(cloud(1.0 + 0.1 * i, seq))
    st = decode(encode(svc.status()), ServiceStatus)
    assert st.events["cloud_seq_jump"] == 4
    assert "clouds_lost_upstream" not in st.events


def test_small_gaps_are_still_counted_as_lost():
    svc = mapper()
    for i, seq in enumerate([1, 2, 5, 5 + MAX_SEQ_GAP, 6 + 2 * MAX_SEQ_GAP]):
        svc.on_cloud(cloud(1.0 + 0.1 * i, seq))
    assert svc.events["clouds_lost_upstream"] == 2 + MAX_SEQ_GAP - 1
    assert svc.events["cloud_seq_jump"] == 1
