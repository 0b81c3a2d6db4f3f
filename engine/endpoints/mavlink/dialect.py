"""pymavlink's ``common`` dialect, MAVLink 2: the tables every module of the endpoint reads
(messages, fields, enums), imported in one place below all of them."""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

__all__ = ["mavlink2"]
