"""What the MQTT pump's session receives, and where each message goes.

One session carries a station's commands (``<base>/cmd/<name>``, and ``<base>/cmd/<door>/<name>``
for each of its named doors, ``mqtt.command_doors``), the site's lives and lives requests (with
``mqtt.share_lives``: gateway/outputs/mqtt/sitelives.py) and the console's site view (other
stations' state and status). :class:`InboundRouter` makes those subscriptions on every connect and
hands each message to its consumer (called on the pump thread): ``on_command(name, payload,
response, source)`` — the source names the door (``mqtt``, ``mqtt:<door>``), so that each door
has its own command budget —, ``on_lives(topic, payload)``, ``on_site(topic, payload)``.

An MQTT 5 command may name where its answer goes (Response Topic, Correlation Data): obeyed only
within the bounds and below the reply prefix (``mqtt.reply_prefix``, default ``<base>/reply``);
anything else is answered on ``reply``.
"""
from __future__ import annotations

import logging
from collections.abc import Callable

import paho.mqtt.client as paho

from ...plumbing.ratelog import RateLog, clip
from . import messages as M
from . import schema
from .settings import MqttSettings
from .sitelives import site_filter

log = logging.getLogger("hookwatch.mqtt")

#: an MQTT 5 Response Topic (characters) / Correlation Data (bytes) longer than this is not used
#: (the reply goes to the ``reply`` topic): a request cannot make the gateway publish much
RESPONSE_TOPIC_MAX = 256
CORRELATION_MAX = 256

#: where an MQTT 5 request wants its answer: (Response Topic, Correlation Data)
Response = tuple[str, bytes | None]
#: ``on_command(name, payload, response, source)``: source ``mqtt`` (the default door) or ``mqtt:<door>``
CommandCallback = Callable[[str, bytes, Response | None, str], None]
#: ``on_lives(topic, payload)`` / ``on_site(topic, payload)``
TopicCallback = Callable[[str, bytes], object]


def join_site(client: paho.Client, s: MqttSettings, lives: bool, filters: tuple[str, ...]) -> None:
    """The site's subscriptions of a connected session: with ``lives``, the site's lives and its
    lives requests, and a request of this station (non-retained: a clustered broker's retained
    store is per node, so a late joiner is never left to it; gateway/outputs/mqtt/sitelives.py);
    and ``filters`` (the console's site view)."""
    if lives:
        client.subscribe(site_filter(s.base_topic), qos=1)
        client.subscribe(schema.lives_request_topic(s.base_topic), qos=1)
    for f in filters:
        client.subscribe(f, qos=1)
    if lives:
        client.publish(schema.lives_request_topic(s.base_topic), s.station_id.encode(), qos=1, retain=False)


class InboundRouter:
    """The subscriptions of one station's session and the routing of what arrives on them (see the
    module docstring); ``counters`` are the pump's."""

    def __init__(self, settings: MqttSettings, counters: dict[str, int], on_command: CommandCallback,
                 on_lives: TopicCallback | None) -> None:
        self.s = settings
        self.counters = counters
        self.on_command = on_command
        #: the site's retained lives and its lives requests (topic, payload), when the station shares them
        self.on_lives = on_lives
        #: more subscriptions of the site (the console's site view: other stations' state and
        #: status) and where their messages go (pump thread); set by :meth:`add_site_feed`
        self._site_filters: tuple[str, ...] = ()
        self.on_site: TopicCallback | None = None
        self._cmd_prefix = M.command_filter(settings.base_topic)[:-1]
        self._doors = tuple(settings.command_doors)
        #: a Response Topic must start with this (the configured reply prefix and a slash)
        self.response_prefix = (settings.reply_prefix or schema.topic_for(settings.base_topic, "reply")) + "/"
        self._refusals = RateLog(log)

    def add_site_feed(self, topic_filters: tuple[str, ...], on_site: TopicCallback) -> None:
        """Also subscribe to ``topic_filters`` (on every connect) and hand what arrives on them to
        ``on_site``."""
        self._site_filters = tuple(topic_filters)
        self.on_site = on_site

    def subscribe(self, client: paho.Client) -> None:
        """The subscriptions of a session the broker just accepted: the commands, then the site's."""
        client.subscribe(M.command_filter(self.s.base_topic), qos=1)
        for door in self._doors:
            client.subscribe(schema.command_door_filter(self.s.base_topic, door), qos=1)
        join_site(client, self.s, self.on_lives is not None, self._site_filters)

    def on_message(self, client: paho.Client | None, userdata: object, msg: paho.MQTTMessage) -> None:
        """paho's ``on_message`` (inside the network loop, on the pump thread)."""
        if not msg.topic.startswith(self._cmd_prefix):
            if self.on_lives is not None and msg.topic.endswith(("/lives", "/" + schema.LIVES_REQUEST)):
                self.counters["site_lives"] += 1
                self.on_lives(msg.topic, bytes(msg.payload))
            elif self.on_site is not None:
                self.counters["site_view"] += 1
                self.on_site(msg.topic, bytes(msg.payload))
            return
        on = schema.parse_command_topic(self.s.base_topic, msg.topic, self._doors)
        if on is None:                  # below cmd/ but on no door of this station
            self.counters["commands_off_door"] += 1
            return
        self.counters["commands"] += 1
        self.on_command(on[0], msg.payload, self.response_of(msg), schema.command_source(on[1]))

    def response_of(self, msg: paho.MQTTMessage) -> Response | None:
        """MQTT 5: where the request wants its answer, ``(Response Topic, Correlation Data)``, if
        it names a topic one may publish to within the bounds and below the reply prefix
        (``mqtt.reply_prefix``, default ``<base>/reply``); None: answer on ``reply``. A request
        allowed to publish on ``cmd/…`` only cannot make the gateway publish on result, state or
        other stations' command topics (or Sparkplug's): such a Response Topic is not obeyed,
        counted (``response_topic_refused``) and logged once a minute with the count."""
        props = getattr(msg, "properties", None)
        topic = getattr(props, "ResponseTopic", None) if props is not None else None
        if topic is None:
            return None
        corr = getattr(props, "CorrelationData", None)
        if (not isinstance(topic, str) or not 0 < len(topic) <= RESPONSE_TOPIC_MAX
                or any(ch in topic for ch in "+#\x00") or topic.startswith("$")
                or (corr is not None and len(corr) > CORRELATION_MAX)):
            self.counters["bad_response_topic"] += 1
            return None
        if not topic.startswith(self.response_prefix):
            self.counters["response_topic_refused"] += 1
            self._refusals.warning("response_topic", "%s: MQTT 5 Response Topic %s is not below %s: not obeyed, "
                                   "answered on reply", self.s.station_id, clip(topic), self.response_prefix)
            return None
        return topic, None if corr is None else bytes(corr)

    def close(self) -> None:
        """The counts of the last refusal window, and no timer after."""
        self._refusals.close()
