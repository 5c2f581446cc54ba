"""A service client in rmw_cyclonedds's request/reply format, written from its sources
(docs/design/actions-and-services.md §1): topics `rq<service>Request` / `rr<service>Reply`,
and before the body a `{uint64 guid; int64 seq}` header the server echoes. Request and
response types declare those two fields first."""

import random
import time

from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from test_dds import ros_qos


class ServiceClient:
    """One client: a random guid, seq counting up; its reply is the one echoing both."""

    def __init__(self, participant, service, request_type, response_type):
        qos = ros_qos(depth=10)
        self.writer = DataWriter(
            participant, Topic(participant, f"rq{service}Request", request_type), qos=qos
        )
        self.reader = DataReader(
            participant, Topic(participant, f"rr{service}Reply", response_type), qos=qos
        )
        self.guid = random.getrandbits(63) | 1
        self.seq = 0
        self.service = service
        self.response_type = response_type

    def wait_for_server(self, deadline):
        """A volatile request written before the server's reader matched would be lost."""
        while not (
            self.writer.get_matched_subscriptions() and self.reader.get_matched_publications()
        ):
            assert time.monotonic() < deadline, f"{self.service}: no server"
            time.sleep(0.05)

    def send(self, make_request):
        """Write `make_request(guid, seq)`; returns the seq to wait for."""
        self.seq += 1
        self.writer.write(make_request(self.guid, self.seq))
        return self.seq

    def reply(self, seq, timeout_s):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for r in self.reader.take(N=10):
                if isinstance(r, self.response_type) and (r.guid, r.seq) == (self.guid, seq):
                    return r
            time.sleep(0.01)
        raise AssertionError(f"{self.service}: no reply to request {seq}")

    def call(self, make_request, timeout_s=10.0):
        """Wait for the server, send, and wait for the reply, all within `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        self.wait_for_server(deadline)
        return self.reply(self.send(make_request), deadline - time.monotonic())
