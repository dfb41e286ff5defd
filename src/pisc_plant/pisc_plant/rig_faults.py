"""The virtual rig's fault requests: what may be asked of it, checked whole.

A request is one JSON object of these keys (:data:`REQUESTS`)::

    {"drop_rate": 0.01}   lose each sent byte with this probability (0..1)
    {"flip_rate": 0.001}  flip one bit of each sent byte with this probability (0..1)
    {"silence_s": 0.1}    send nothing for this long (the device goes quiet; 0 .. 3600 s)
    {"garbage": 20}       send this many random bytes before the next frame (0..1024)
    {"status": true}      print the rig's status as one JSON line
    {"quit": true}        stop

:func:`check_request` refuses anything else (an unknown key, a value of the wrong type,
not finite, negative or out of range) whole, with a :class:`RequestError` naming the
key and the rule; :class:`RigFaults` holds the faults in force
(:mod:`pisc_plant.virtual_rig` applies them).
"""

from __future__ import annotations

import difflib
import json
import math
from dataclasses import dataclass
from typing import Any

__all__ = ["MAX_GARBAGE", "MAX_REQUEST", "REQUESTS", "RequestError", "RigFaults",
           "check_request"]

MAX_GARBAGE = 1024  # bytes per request: 89 ms of the line at 115200 baud
MAX_REQUEST = 4096  # bytes of one request line


class RequestError(ValueError):
    """A fault request the rig refuses; the message names the key and the rule."""


def _number(key: str, value: Any, rule: str) -> float:
    """``value`` as a finite float, or RequestError naming ``key`` and ``rule``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RequestError(f"{key} = {json.dumps(value)} must be a number ({rule}), "
                           f"not {_json_type(value)}")
    try:
        number = float(value)
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        raise RequestError(f"{key} = {json.dumps(value)} must be a finite number ({rule})")
    return number


def _json_type(value: Any) -> str:
    for cls, name in ((bool, "true/false"), ((int, float), "a number"), (str, "a string"),
                      (list, "a list"), (dict, "an object"), (type(None), "null")):
        if isinstance(value, cls):
            return name
    return type(value).__name__


def _probability(key: str, value: Any) -> float:
    rule = "a probability per byte, 0 to 1"
    number = _number(key, value, rule)
    if not 0.0 <= number <= 1.0:
        raise RequestError(f"{key} = {json.dumps(value)} must lie in [0, 1] ({rule})")
    return number


MAX_SILENCE_S = 3600.0  # a longer silence is no test of a link (1e308 was taken)


def _silence(key: str, value: Any) -> float:
    rule = f"seconds without frames, 0 .. {MAX_SILENCE_S:g}"
    number = _number(key, value, rule)
    if number < 0.0:
        raise RequestError(f"{key} = {json.dumps(value)} must not be negative ({rule})")
    if number > MAX_SILENCE_S:
        raise RequestError(f"{key} = {json.dumps(value)} is too long ({rule})")
    return number


def _garbage(key: str, value: Any) -> int:
    rule = f"random bytes to send, a whole number from 0 to {MAX_GARBAGE}"
    number = _number(key, value, rule)
    if number != math.floor(number) or not 0 <= number <= MAX_GARBAGE:
        raise RequestError(f"{key} = {json.dumps(value)} must be a whole number from 0 to "
                           f"{MAX_GARBAGE} (random bytes to send before the next frame)")
    return int(number)


def _flag(key: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise RequestError(f"{key} = {json.dumps(value)} must be true or false, "
                           f"not {_json_type(value)}")
    return value


REQUESTS = {"drop_rate": _probability, "flip_rate": _probability, "silence_s": _silence,
            "garbage": _garbage, "status": _flag, "quit": _flag}


def check_request(request: Any) -> dict[str, Any]:
    """A fault request (a parsed JSON value) checked whole: the values to apply, or
    RequestError for the first key that breaks its rule (nothing is applied then)."""
    if not isinstance(request, dict):
        raise RequestError(f"a request is a JSON object of {', '.join(REQUESTS)}; "
                           f"got {_json_type(request)}")
    checked = {}
    for key, value in request.items():
        if key not in REQUESTS:
            match = difflib.get_close_matches(key, list(REQUESTS), n=1)
            hint = f"; did you mean {match[0]}?" if match else ""
            raise RequestError(f"{json.dumps(key)} is not a request (known: "
                               f"{', '.join(REQUESTS)}){hint}")
        checked[key] = REQUESTS[key](key, value)
    return checked


@dataclass
class RigFaults:
    drop_rate: float = 0.0
    flip_rate: float = 0.0
    silent_until: float = -math.inf  # monotonic time
    garbage: int = 0

    def update(self, request: dict[str, Any], now: float) -> None:
        """Apply a request (:func:`check_request` first: all of it or, refused, none)."""
        request = check_request(request)
        if self.garbage + request.get("garbage", 0) > MAX_GARBAGE:
            raise RequestError(f"garbage = {request['garbage']}: {self.garbage} bytes are "
                               f"already waiting, and at most {MAX_GARBAGE} may")
        for key in ("drop_rate", "flip_rate"):
            if key in request:
                setattr(self, key, request[key])
        if "silence_s" in request:
            self.silent_until = now + request["silence_s"]
        self.garbage += request.get("garbage", 0)
