"""Topic names and QoS shared by the brain and its input nodes (no node code)."""

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

MANUAL_COMMAND = "manual_command"
CANCEL_COMMAND = "cancel_command"
TASK_STATUS = "task_status"
#: The brain's acknowledged way in (decision_maker_interfaces/srv/SubmitCommand).
SUBMIT_COMMAND = "submit_command"
#: The brain's own stop for the hardware layer (on timeouts). Separate from /cancel_command, so that
#: every /cancel_command the brain receives comes from someone else and always cancels.
HARDWARE_STOP = "hardware_stop"
OBJECT_LIST = "object_list"

#: Commands: reliable with a deep history, so a burst is queued, not dropped.
COMMAND_QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
#: /task_status, publisher and every subscriber: one update per state change, so a burst of N commands
#: makes more than N updates at once (each one's "queued" or "rejected", the running one's steps).
#: A reliable keep-last writer overwrites what a slow reader has not yet acknowledged, so the history
#: is twice the largest burst tested (1000 requests, test_reliability_ros): at depth 200 a loaded
#: reader once missed the running command's "running" among a thousand "rejected".
STATUS_QOS = QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE)
#: The brain's /task_status publisher: STATUS_QOS, and transient local, so it keeps its last 2000 updates for
#: readers that ask for them (compatible with STATUS_QOS's volatile readers, which get live updates only). A reader
#: that must not miss an update uses STATUS_HISTORY_QOS: one that joins late, and one that is matched again after a
#: participant lease ran out (a process stalled longer than the lease, 2 s in scripts/env.sh's Fast DDS profile):
#: DDS delivers nothing a writer publishes while the match is gone, so a volatile reader misses those updates for
#: good (test_reliability_ros: the brain thawed after a freeze, its "#1 running" never reached the operator).
STATUS_PUBLISHER_QOS = QoSProfile(depth=2000, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                  reliability=ReliabilityPolicy.RELIABLE)
#: A /task_status reader that gets the kept updates when matched (again). It may receive an update twice (when
#: its side lost and found the brain again): identical messages are the same update.
STATUS_HISTORY_QOS = STATUS_PUBLISHER_QOS
#: The submit_command service (requests and replies): deep, so a burst is queued, not overwritten
#: (the services default, depth 10, drops a burst silently). A sender that still gets no answer
#: is told so by its own deadline (CommandClient), never left guessing. Twice the largest burst tested
#: (1000 requests, test_reliability_ros): at exactly 1000 one request went unanswered once in a loaded run.
SERVICE_QOS = QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE)
CANCEL_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
#: Latched like the object database publishes it.
OBJECT_LIST_QOS = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
