"""ROS 2 interop: publish and follow ``/clock``, and subscribe to stamped topics, over DDS
(ROS's default middleware, through Cyclone DDS) or Zenoh (rmw_zenoh's wire format).

No ROS installation is needed: evclock puts on the wire what a ROS 2 node puts there. The
middleware is chosen as a ROS node chooses it: ``rmw=`` (``"dds"``/``"zenoh"``), else
``RMW_IMPLEMENTATION``, else DDS. Install the extra first::

    pip install 'evclock[ros2]'

* :class:`Ros2ClockPublisher` publishes a simulation's time as ``/clock`` (``evclock run SIM
  --ros2-clock``; ``--ros2`` adds ``/joint_states``, ``/tf``, ``/tf_static``): ROS 2 nodes with
  ``use_sim_time:=true`` follow it.
* :class:`Ros2ClockSource` is a time source that follows a ROS 2 ``/clock``
  (``EVCLOCK_CLOCK=ros2:///clock`` or ``evclock.run(main(), clock="ros2:///clock")``).
* :func:`subscribe` turns a ROS 2 topic into a filter of :class:`~evclock.data.Stamped`
  messages for evclock's synchronisers and caches.
* The Zenoh wire format itself (key expressions, CDR payload, attachments, liveliness tokens) is
  exposed for tests and tools: :func:`clock_key_expr`, :func:`encode_clock`,
  :func:`decode_clock`, :func:`encode_attachment`, :data:`WIRE_FORMATS`.

Importing this module imports neither Zenoh nor Cyclone DDS; opening a publisher, a source or
a subscription does.
"""

from evclock._errors import Ros2MessageError, Ros2SubscribersError
from evclock.ros2._publisher import Ros2ClockPublisher
from evclock.ros2._rmw import ENV_RMW_IMPLEMENTATION, MIDDLEWARES, RMW_IMPLEMENTATIONS
from evclock.ros2._session import DEFAULT_CONNECT, DEFAULT_LISTEN
from evclock.ros2._source import DEFAULT_SILENCE_TIMEOUT, Ros2ClockSource
from evclock.ros2._subscribe import Ros2Subscription, subscribe
from evclock.ros2._url import source_from_url
from evclock.ros2._wire import (
    CLOCK_DDS_TYPE,
    CLOCK_QOS,
    CLOCK_TYPE,
    CLOCK_TYPE_HASH,
    DEFAULT_WIRE_FORMAT,
    ENV_ROS_DOMAIN_ID,
    HUMBLE_TYPE_HASH,
    WIRE_FORMATS,
    WireFormat,
    clock_key_expr,
    decode_clock,
    encode_attachment,
    encode_clock,
    endpoint_token,
    entity_gid,
    node_token,
    resolve_domain_id,
)

__all__ = [
    "Ros2MessageError",
    "Ros2SubscribersError",
    "CLOCK_DDS_TYPE",
    "CLOCK_QOS",
    "CLOCK_TYPE",
    "CLOCK_TYPE_HASH",
    "DEFAULT_CONNECT",
    "DEFAULT_LISTEN",
    "DEFAULT_SILENCE_TIMEOUT",
    "DEFAULT_WIRE_FORMAT",
    "ENV_RMW_IMPLEMENTATION",
    "ENV_ROS_DOMAIN_ID",
    "MIDDLEWARES",
    "RMW_IMPLEMENTATIONS",
    "HUMBLE_TYPE_HASH",
    "WIRE_FORMATS",
    "Ros2ClockPublisher",
    "Ros2ClockSource",
    "Ros2Subscription",
    "WireFormat",
    "clock_key_expr",
    "decode_clock",
    "encode_attachment",
    "encode_clock",
    "endpoint_token",
    "entity_gid",
    "node_token",
    "resolve_domain_id",
    "source_from_url",
    "subscribe",
]

Ros2MessageError.__module__ = __name__
Ros2SubscribersError.__module__ = __name__
