"""An event's server-sent frame keeps its JSON on one line for every client's line splitting: stored JSON passes
through the hot reads as text (kernel/fast_reads.py) and orjson writes non-ASCII as is."""
from __future__ import annotations

import json

import orjson

from app.jobs.outputs import sse_event


def test_an_event_is_one_data_line_whatever_its_text():
    message = "a\u2028b\u2029c\x85d\ne\r\nf"
    stored = '{\n  "where": "x\\u2028y",\r\n  "n": [1,\n 2]\n}'  # a JSON column as some writer may have kept it
    frame = sse_event({"id": 7, "object": "job.event", "type": "log", "message": message,
                       "data": orjson.Fragment(stored)})
    lines = frame.splitlines()  # what httpx's iter_lines does: it also breaks at NEL, U+2028 and U+2029
    assert lines == [lines[0], lines[1], lines[2], ""] and frame.endswith("\n\n")
    assert lines[:2] == ["id: 7", "event: log"] and lines[2].startswith("data: ")
    assert json.loads(lines[2].removeprefix("data: ")) == {"id": 7, "object": "job.event", "type": "log",
                                                           "message": message, "data": json.loads(stored)}
