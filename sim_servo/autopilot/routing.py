"""MAVLink routing between the autopilot's links: where each sender is, what to forward where,
and whether a frame is (also) for the autopilot itself. Forwarded frames go out as received (a
signed frame keeps its signature); nothing goes back out of the link it came in on.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.params import ParamTable
from sim_servo.autopilot.state import AutopilotState
from sim_servo.autopilot.wire import Wire

#: MAVLink_routing.h: the routing table holds at most this many (system, component, link).
MAX_ROUTES = 20
#: Handled here and never forwarded (MAVLink_routing.cpp ``check_and_forward``): RADIO and
#: RADIO_STATUS are about the link itself, ADSB_VEHICLE has its own stream.
NOT_FORWARDED_IDS = frozenset(
    {
        mavlink.MAVLINK_MSG_ID_RADIO,
        mavlink.MAVLINK_MSG_ID_RADIO_STATUS,
        mavlink.MAVLINK_MSG_ID_ADSB_VEHICLE,
    }
)
#: Our links as PX4 MAVLink instances, for their ``MAV_n_FORWARD``: the companion's link (0)
#: is instance 1 (TELEM2), the ground station's (1) instance 0 (TELEM1), as on a Pixhawk.
PX4_FORWARD_PARAMS = {0: "MAV_1_FORWARD", 1: "MAV_0_FORWARD"}


class Router(ABC):
    """Routing state common to both firmwares: the peer last heard, the links active since boot
    and ArduPilot's routing table (empty on PX4). A reboot forgets all of it."""

    def __init__(self, state: AutopilotState, wire: Wire) -> None:
        self._state = state
        self._wire = wire
        own = state.config
        self._own = (own.system_id, own.component_id)
        #: ArduPilot's routing table: (system, component, link) in the order learned, at most
        #: MAX_ROUTES, never forgotten (only a reboot clears it).
        self.routes: list[tuple[int, int, int]] = []
        #: Links a frame was received on since boot (ArduPilot's ``active_channel_mask``).
        self.active_links: set[int] = set()
        #: The (system, component) of the last HEARTBEAT received.
        self.peer: tuple[int, int] | None = None
        self._peers_seen: set[tuple[int, int]] = set()

    def route(self, msg: mavlink.MAVLink_message, channel: int, now_s: float) -> bool:
        """Learn where ``msg`` came from and forward it; True if it is (also) for us."""
        self.active_links.add(channel)
        return self._route(msg, channel, now_s)

    @abstractmethod
    def _route(self, msg: mavlink.MAVLink_message, channel: int, now_s: float) -> bool: ...

    def on_heartbeat(self, msg: Any, now_s: float, channel: int) -> None:
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        self.peer = source
        if source not in self._peers_seen:
            self._peers_seen.add(source)
            self._state.emit(
                now_s, "peer", src=list(source), type=msg.type, autopilot=msg.autopilot
            )

    def boot(self, now_s: float) -> None:
        self.routes.clear()
        self.active_links.clear()
        self.peer = None
        self._peers_seen.clear()

    def _forward(
        self,
        msg: mavlink.MAVLink_message,
        links: list[int],
        now_s: float,
        source: tuple[int, int],
        target: tuple[int, int],
        *,
        log: bool = True,
        delay_s: float = 0.0,
    ) -> None:
        frame = bytes(msg.get_msgbuf())
        for link in links:
            self._wire.write_routed(frame, link, now_s, delay_s)
            self._state.stats["routed"] += 1
        if links and log:
            self._state.emit(
                now_s,
                "routed",
                msg=msg.get_type(),
                src=list(source),
                to=list(target),
                links=links,
            )


class ArduPilotRouter(Router):
    """ArduPilot's rules, libraries/GCS_MAVLink/MAVLink_routing.cpp ``check_and_forward``:

    * our own (system, component) looped back: handled, neither learned nor forwarded;
    * every other source is learned as (system, component, link), never forgotten (a
      reboot clears the table), at most MAX_ROUTES entries;
    * RADIO, RADIO_STATUS, ADSB_VEHICLE: handled, not forwarded; HEARTBEAT: handled and
      forwarded to every active link but its own and those its sender was heard on;
    * target (system, component) ours: handled only;
    * otherwise forwarded to each link (never the one it came in on) with a route that
      matches: target system 0 or absent, any route; else the route's system and, for our
      own system, its component (or target component 0/absent); for another system, any
      of its components;
    * for our system and not forwarded anywhere (a component never heard, or heard only on
      the link the frame came in on): handled here, so a command gets our UNSUPPORTED. Routes
      are never forgotten, so frames for a companion that left still go to its dead link.
    """

    def _route(self, msg: mavlink.MAVLink_message, channel: int, now_s: float) -> bool:
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        own = self._own
        if source == own:
            return True
        self._learn_route(source, channel)
        msg_id = msg.get_msgId()
        if msg_id in NOT_FORWARDED_IDS:
            return True
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            heard_on = {link for s, c, link in self.routes if (s, c) == source}
            others = sorted(self.active_links - {channel} - heard_on)
            self._forward(msg, others, now_s, source, (0, 0), log=False)
            return True
        target_system = getattr(msg, "target_system", -1)
        target_component = getattr(msg, "target_component", -1)
        broadcast_system = target_system in (0, -1)
        broadcast_component = target_component in (0, -1)
        match_system = broadcast_system or target_system == own[0]
        process_locally = match_system and (broadcast_component or target_component == own[1])
        if process_locally and not broadcast_system and not broadcast_component:
            return True
        links: list[int] = []
        for system, component, link in self.routes:
            matches = broadcast_system or (
                target_system == system
                and (broadcast_component or target_component == component or not match_system)
            )
            if matches and link != channel and link not in links:
                links.append(link)
        self._forward(msg, links, now_s, source, (target_system, target_component))
        if not links and match_system:
            process_locally = True
        return process_locally

    def _learn_route(self, source: tuple[int, int], channel: int) -> None:
        route = (*source, channel)
        if source[0] != 0 and route not in self.routes and len(self.routes) < MAX_ROUTES:
            self.routes.append(route)


class Px4Router(Router):
    """PX4's routing (mavlink_main.cpp ``forward_message``, mavlink_receiver.cpp):

    * each link remembers the (system, component)s heard on it (``component_was_seen``);
    * a frame is forwarded only when forwarding is on for the link it came in on *and* for
      the link it goes out on (``MAV_n_FORWARD``, see :data:`PX4_FORWARD_PARAMS`), never
      back out of its own link, and only to a link that has heard its target (a target
      system 0, or no target: a link that has heard anyone; component 0: any component
      of the system); a forwarded frame waits ``forward_delay_ms`` before its link's pass;
    * handled here when its target is us or a broadcast; a command for another component
      of our system is otherwise ignored, without an answer ("Ignore command 31010 from
      255/190 to 1/191" in PX4's log), whether or not it was forwarded.
    """

    def __init__(self, state: AutopilotState, wire: Wire, params: ParamTable) -> None:
        super().__init__(state, wire)
        self._params = params
        #: The (system, component)s each link has heard (``component_was_seen``).
        self._heard: dict[int, set[tuple[int, int]]] = {}

    def boot(self, now_s: float) -> None:
        super().boot(now_s)
        self._heard.clear()

    def _route(self, msg: mavlink.MAVLink_message, channel: int, now_s: float) -> bool:
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        own = self._own
        if source == own:
            return True
        if source[0] != 0:
            self._heard.setdefault(channel, set()).add(source)
        target_system = max(0, getattr(msg, "target_system", 0))
        target_component = max(0, getattr(msg, "target_component", 0))
        local = target_system in (0, own[0]) and target_component in (0, own[1])
        if (target_system, target_component) != own and self.forwarding(channel):
            links = [
                link
                for link in range(len(self._wire.links))
                if link != channel
                and self.forwarding(link)
                and self._was_seen(link, target_system, target_component)
            ]
            if links:
                delay_s = self._state.config.px4_timing.forward_delay_ms / 1000.0
                self._forward(
                    msg, links, now_s, source, (target_system, target_component), delay_s=delay_s
                )
        is_command = msg.get_type() in ("COMMAND_LONG", "COMMAND_INT")
        if not local and is_command and target_system == own[0]:
            self._state.emit(
                now_s,
                "ignored",
                command=msg.command,
                src=list(source),
                to=[target_system, target_component],
            )
        return local

    def forwarding(self, channel: int) -> bool:
        """Whether the MAVLink instance on ``channel`` forwards (``MAV_n_FORWARD``)."""
        name = PX4_FORWARD_PARAMS.get(channel)
        return name is not None and self._params[name].value != 0

    def _was_seen(self, channel: int, system: int, component: int) -> bool:
        heard = self._heard.get(channel, set())
        if system == 0:
            return bool(heard)
        return any(s == system and component in (0, c) for s, c in heard)
