"""Outbox: whole messages, a started one completed first, oldest dropped over the bound."""

from __future__ import annotations

from collections import Counter

from ceilkit.runtime.io.link.outbox import Outbox


def make(max_bytes):
    counts = Counter()
    box = Outbox(max_bytes, lambda: 0, lambda: "test", lambda **inc: counts.update(inc))
    return box, counts


def test_started_message_is_completed_before_the_next():
    box, counts = make(100)
    box.put(b"AAAAAAAAAA")
    box.put(b"BBBBB")
    out = bytearray()
    budget = [4]

    def write(data):
        n = min(len(data), budget[0])
        out.extend(data[:n])
        budget[0] -= n
        return n

    box.pump(write)
    assert bytes(out) == b"AAAA" and box.pending_bytes == 11
    budget[0] = 100
    box.pump(write)
    assert bytes(out) == b"AAAAAAAAAABBBBB" and box.pending_bytes == 0
    assert counts == {"sent": 2, "bytes_sent": 15}


def test_oldest_unstarted_dropped_over_the_bound_and_stall_ends_when_flowing():
    box, counts = make(20)
    for m in (b"1" * 8, b"2" * 8, b"3" * 8):
        box.put(m)
    assert counts["dropped"] == 1 and box.stalled and box.pending_bytes == 16
    out = bytearray()
    box.pump(lambda d: out.extend(d) or len(d))
    assert bytes(out) == b"2" * 8 + b"3" * 8 and not box.stalled


def test_clear_counts_what_was_lost_including_a_started_message():
    box, _ = make(100)
    box.put(b"abcdef")
    box.put(b"gh")
    box.pump(lambda d: 2 if d == b"abcdef" else 0)
    assert box.clear() == 2 and box.pending_bytes == 0 and not box.stalled
