"""Reading and writing MCAP recordings under the aeromag channel contract."""

from pipeline.flight import Flight
from pipeline.io.contract import INPUT_CONTRACT, TopicRule, rule_for_topic
from pipeline.io.reader import read_flight, read_topics
from pipeline.io.writer import McapOutput, OutputChannel, stamp, write_with_new_channels

__all__ = [
    "INPUT_CONTRACT",
    "Flight",
    "McapOutput",
    "OutputChannel",
    "TopicRule",
    "read_flight",
    "read_topics",
    "rule_for_topic",
    "stamp",
    "write_with_new_channels",
]
