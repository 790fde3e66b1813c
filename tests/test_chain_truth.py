"""The end-to-end judge's ground truth (``operator_site.chain._Truth``) follows the link's
session: after a renewal (``WorkSiteLink.session`` is a new session, the old one closed) it is
still heard. Real zenoh sessions on loopback; the link is a stand-in holding them."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pytest
import zenoh

from operator_site.chain import _Truth
from protocol import ObjectPose, TruthPoses, encode, key, make_config
from tests.conftest import free_port

pytestmark = pytest.mark.integration


@dataclass
class _Link:
    session: zenoh.Session
    site_id: str = "truth-test"


def test_the_truth_is_heard_on_the_links_new_session_after_a_renewal() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(make_config(listen=[endpoint])) as work_site:
        first = zenoh.open(make_config(connect=[endpoint]))
        link = _Link(first)
        truth = _Truth(link)  # type: ignore[arg-type]

        def publish(seq: int) -> float:
            stamp_s = time.time()
            poses = (ObjectPose("cube", np.eye(4)),)
            work_site.put(key(link.site_id, "truth"), encode(TruthPoses(seq, stamp_s, poses)))
            return stamp_s

        def heard(seq: int) -> TruthPoses:
            deadline = time.monotonic() + 10.0
            while True:  # (the subscriber is declared a moment before it matches)
                stamp_s = publish(seq)
                try:
                    return truth.latest_after(stamp_s, timeout_s=0.5)
                except TimeoutError:
                    if time.monotonic() > deadline:
                        raise

        assert heard(1).seq == 1
        second = zenoh.open(make_config(connect=[endpoint]))
        link.session = second  # renewed: the old session closed
        first.close()
        try:
            assert heard(2).seq == 2
        finally:
            second.close()
