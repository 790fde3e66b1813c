"""What a caller follows on a link (``WorkSiteLink.follow``, as the end-to-end judge's ground
truth in ``operator_site.chain._Truth``) is still heard after the link renewed its session (a
new session once the work site was lost, the old one closed). Real zenoh sessions on loopback; a
stand-in work site that only publishes."""

from __future__ import annotations

import time

import numpy as np
import pytest
import zenoh

from operator_site.chain import _Truth
from operator_site.link import WorkSiteLink
from protocol import ObjectPose, TruthPoses, encode, key, make_config
from tests.conftest import free_port

pytestmark = pytest.mark.integration


def test_the_truth_is_heard_on_the_links_new_session_after_a_renewal() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(make_config(listen=[endpoint])) as work_site:
        link = WorkSiteLink(make_config(connect=[endpoint]), "truth-test", heartbeat_process=False)
        try:
            truth = _Truth(link)

            def heard(seq: int) -> TruthPoses:
                deadline = time.monotonic() + 10.0
                while True:  # (a subscriber is declared a moment before it matches)
                    stamp_s = time.time()
                    poses = (ObjectPose("cube", np.eye(4)),)
                    payload = encode(TruthPoses(seq, stamp_s, poses))
                    work_site.put(key(link.site_id, "truth"), payload)
                    try:
                        return truth.latest_after(stamp_s, timeout_s=0.5)
                    except TimeoutError:
                        if time.monotonic() > deadline:
                            raise

            assert heard(1).seq == 1
            first = link.session
            link._renew()  # what losing the work site does
            link._renewing.join(timeout=30)
            assert link.session is not first and first.is_closed()
            assert heard(2).seq == 2
        finally:
            link.close()
