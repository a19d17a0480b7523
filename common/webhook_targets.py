"""Where webhooks may be sent: public addresses only, unless the operator allows more (issue #56).

A webhook's URL comes from an API client, and the dispatcher POSTs to it from inside the operator's network, so
an unchecked URL lets any client reach loopback services, cloud metadata (169.254.169.254) or the internal
network on the service's behalf (server-side request forgery). ``WebhookTargets`` refuses loopback, private,
link-local, multicast, unspecified, reserved and other not globally routable addresses, IPv4 and IPv6 alike,
including the IPv4 address inside an IPv4-mapped or 6to4 IPv6 address, unless ``webhook_allow_targets``
(``HOI_REFINE_WEBHOOK_ALLOW_TARGETS``) names the host or a range holding the address.

Registration checks every address the host resolves to (``check_url``). Each delivery resolves the host again,
checks again and hands back the one address to connect to (``pin``): the dispatcher connects to that address
itself, so a name that resolves elsewhere between the check and the connection (DNS rebinding) cannot slip
through. Name resolution goes through ``resolver`` only (the seam tests replace).
"""

from __future__ import annotations

import ipaddress
import socket
from collections.abc import Callable
from dataclasses import dataclass
from urllib.parse import urlsplit

from common.errors import FieldProblem, InvalidRequestError

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network
#: (host, port) -> the addresses a connection to it may use, in the order to try them.
Resolver = Callable[[str, int], list[IPAddress]]
DEFAULT_PORTS = {"http": 80, "https": 443}


class TargetRefusedError(Exception):
    """A webhook URL may not be sent to; the message says why (shown to the client and in the delivery log)."""


def system_resolver(host: str, port: int) -> list[IPAddress]:
    """The operating system's resolver (``getaddrinfo``), each address once, in its order."""
    found: list[IPAddress] = []
    for *_, sockaddr in socket.getaddrinfo(host, port, type=socket.SOCK_STREAM):
        address = ipaddress.ip_address(str(sockaddr[0]).split("%", 1)[0])  # an IPv6 scope does not matter here
        if address not in found:
            found.append(address)
    return found


def refusal(address: IPAddress) -> str | None:
    """Why ``address`` is not a public destination (its class), or None when it is."""
    if isinstance(address, ipaddress.IPv6Address):
        embedded = address.ipv4_mapped or address.sixtofour
        if embedded is not None:
            inner = refusal(embedded)
            return None if inner is None else f"{inner} (IPv4 {embedded} inside IPv6)"
        if address.is_site_local:
            return "site-local"
    checks = (
        ("unspecified", address.is_unspecified), ("loopback", address.is_loopback),
        ("link-local", address.is_link_local), ("multicast", address.is_multicast),
        ("reserved", address.is_reserved), ("private", address.is_private),
        ("not globally routable", not address.is_global),
    )  # fmt: skip
    return next((name for name, hit in checks if hit), None)


def parse_allow_list(text: str) -> tuple[frozenset[str], tuple[IPNetwork, ...]]:
    """``"hooks.internal, 10.8.0.0/16, 127.0.0.1"`` -> (host names, ranges). An address alone is a one-address
    range. ``ValueError`` names an entry that is neither."""
    names: set[str] = set()
    networks: list[IPNetwork] = []
    for entry in (e.strip() for e in text.replace(";", ",").split(",")):
        if not entry:
            continue
        try:
            networks.append(ipaddress.ip_network(entry.strip("[]"), strict=False))
            continue
        except ValueError:
            pass
        name = entry.lower().rstrip(".")
        if not name or any(c in name for c in "/:@ ") or name.startswith("."):
            raise ValueError(f"{entry!r} is neither a host name nor an address range (CIDR)")
        names.add(name)
    return frozenset(names), tuple(networks)


@dataclass(frozen=True)
class PinnedTarget:
    """A checked destination: connect to ``address``; ``host`` is the URL's host (Host header, TLS name)."""

    url: str
    host: str
    port: int
    address: IPAddress


class WebhookTargets:
    """The target policy: public addresses, plus the operator's allowed host names and ranges."""

    def __init__(self, allow: str = "", resolver: Resolver = system_resolver) -> None:
        self.allowed_names, self.allowed_networks = parse_allow_list(allow)
        self.resolver = resolver

    def check_url(self, url: str) -> None:
        """At registration: a 422 naming ``url`` unless every address its host resolves to may be sent to."""
        try:
            self.pin(url)
        except TargetRefusedError as exc:
            raise InvalidRequestError([FieldProblem("url", str(exc))]) from exc

    def pin(self, url: str) -> PinnedTarget:
        """Resolve the URL's host now and return the address to connect to; ``TargetRefusedError`` if the host
        is not allowed, does not resolve, or any of its addresses is refused."""
        parts = urlsplit(url)
        host = (parts.hostname or "").rstrip(".")
        if parts.scheme not in DEFAULT_PORTS or not host:
            raise TargetRefusedError("must be an http:// or https:// URL with a host")
        try:
            port = parts.port or DEFAULT_PORTS[parts.scheme]
        except ValueError as exc:
            raise TargetRefusedError("has an invalid port") from exc
        addresses = self._addresses(host, port)
        if host.lower() not in self.allowed_names:
            for address in addresses:
                why = refusal(address)
                if why is not None and not any(address in net for net in self.allowed_networks):
                    named = "" if str(address) == host else f"host {host!r} resolves to "
                    raise TargetRefusedError(
                        f"{named}{address}, which is {why}: webhooks go to public addresses only "
                        "(an operator allows more with HOI_REFINE_WEBHOOK_ALLOW_TARGETS)"
                    )
        return PinnedTarget(url, host, port, addresses[0])

    def _addresses(self, host: str, port: int) -> list[IPAddress]:
        try:
            return [ipaddress.ip_address(host)]
        except ValueError:
            pass  # a name, not an address
        try:
            addresses = self.resolver(host, port)
        except (OSError, UnicodeError) as exc:
            raise TargetRefusedError(f"host {host!r} does not resolve ({type(exc).__name__})") from exc
        if not addresses:
            raise TargetRefusedError(f"host {host!r} does not resolve")
        return addresses
