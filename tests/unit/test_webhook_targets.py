"""The webhook target policy (common/webhook_targets.py): every class of non-public address is refused, IPv4 and
IPv6 alike (IPv4 inside IPv4-mapped and 6to4 IPv6 too), a name is judged by what it resolves to (through the
resolver seam, never the network), and the operator's allow list lets named hosts and ranges through."""

from __future__ import annotations

import ipaddress

import pytest
from pydantic import ValidationError

from common.errors import InvalidRequestError
from common.settings import Settings
from common.webhook_targets import (
    IPAddress,
    Resolver,
    TargetRefusedError,
    WebhookTargets,
    parse_allow_list,
    refusal,
)

#: One address per refused class, and the class ``refusal`` names.
REFUSED = [
    ("127.0.0.1", "loopback"), ("127.255.0.9", "loopback"), ("::1", "loopback"),
    ("10.1.2.3", "private"), ("172.16.0.1", "private"), ("192.168.1.1", "private"), ("fc00::1", "private"),
    ("fd12:3456::1", "private"),
    ("169.254.169.254", "link-local"), ("fe80::1", "link-local"),
    ("224.0.0.1", "multicast"), ("239.255.255.250", "multicast"), ("ff02::1", "multicast"),
    ("ff0e::1", "multicast"),
    ("0.0.0.0", "unspecified"), ("::", "unspecified"),
    ("240.0.0.1", "reserved"), ("255.255.255.255", "reserved"), ("::7f00:1", "reserved"),
    ("64:ff9b::a00:1", "reserved"),
    ("100.64.0.1", "not globally routable"), ("192.0.2.1", "private"), ("198.18.0.1", "private"),
    ("2001:db8::1", "private"), ("fec0::1", "site-local"),
    ("::ffff:127.0.0.1", "loopback (IPv4 127.0.0.1 inside IPv6)"),
    ("::ffff:169.254.169.254", "link-local (IPv4 169.254.169.254 inside IPv6)"),
    ("::ffff:10.0.0.1", "private (IPv4 10.0.0.1 inside IPv6)"),
    ("2002:7f00:1::", "loopback (IPv4 127.0.0.1 inside IPv6)"),
    ("2002:a9fe:a9fe::1", "link-local (IPv4 169.254.169.254 inside IPv6)"),
]  # fmt: skip
PUBLIC = ["8.8.8.8", "151.101.1.69", "2606:4700:4700::1111", "::ffff:8.8.8.8", "2002:808:808::1"]


@pytest.mark.parametrize(("address", "why"), REFUSED)
def test_every_non_public_class_is_refused(address: str, why: str) -> None:
    assert refusal(ipaddress.ip_address(address)) == why


@pytest.mark.parametrize("address", PUBLIC)
def test_public_addresses_pass(address: str) -> None:
    assert refusal(ipaddress.ip_address(address)) is None


def fixed(table: dict[str, list[str]]) -> Resolver:
    def resolve(host: str, port: int) -> list[IPAddress]:
        if host not in table:
            raise OSError(f"unknown host {host}")
        return [ipaddress.ip_address(a) for a in table[host]]

    return resolve


@pytest.mark.parametrize(("address", "why"), REFUSED)
def test_urls_naming_or_resolving_to_a_refused_address_are_a_422_naming_url(address: str, why: str) -> None:
    targets = WebhookTargets(resolver=fixed({"hooks.example.com": [address]}))
    literal = f"[{address}]" if ":" in address else address
    for url in (f"http://{literal}:8080/hook", "https://hooks.example.com/hook"):
        with pytest.raises(InvalidRequestError) as caught:
            targets.check_url(url)
        (problem,) = caught.value.problems
        shown = str(ipaddress.ip_address(address))  # Python 3.11 writes ::ffff:10.0.0.1 as ::ffff:a00:1
        assert problem.field == "url" and why in problem.problem and shown in problem.problem, problem


def test_a_name_with_one_refused_address_among_public_ones_is_refused() -> None:
    targets = WebhookTargets(resolver=fixed({"mixed.example": ["8.8.8.8", "10.0.0.7"]}))
    with pytest.raises(TargetRefusedError, match=r"resolves to 10\.0\.0\.7, which is private"):
        targets.pin("http://mixed.example/")


def test_a_public_name_is_pinned_to_its_checked_address() -> None:
    targets = WebhookTargets(resolver=fixed({"hooks.example.com": ["151.101.1.69", "8.8.8.8"]}))
    pinned = targets.pin("https://hooks.example.com:8443/x?y=1")
    assert (pinned.host, pinned.port, str(pinned.address)) == ("hooks.example.com", 8443, "151.101.1.69")


def test_unresolvable_names_and_other_schemes_are_refused() -> None:
    targets = WebhookTargets(resolver=fixed({}))
    with pytest.raises(TargetRefusedError, match="does not resolve"):
        targets.pin("http://nowhere.example/")
    with pytest.raises(TargetRefusedError, match="http:// or https://"):
        targets.pin("ftp://8.8.8.8/")


def test_the_allow_list_lets_named_hosts_and_ranges_through() -> None:
    resolve = fixed({"hooks.internal": ["10.8.0.5"], "db.internal": ["10.9.0.5"], "localhost": ["127.0.0.1", "::1"]})
    targets = WebhookTargets("Hooks.Internal., 10.20.0.0/16, ::1, 127.0.0.1", resolver=resolve)
    assert str(targets.pin("http://hooks.internal:9000/").address) == "10.8.0.5"  # named: any address
    assert str(targets.pin("http://10.20.3.4/").address) == "10.20.3.4"
    assert str(targets.pin("http://localhost/").address) == "127.0.0.1"  # both its addresses are allowed
    for url in ("http://db.internal/", "http://10.21.0.1/", "http://169.254.169.254/"):
        with pytest.raises(TargetRefusedError):
            targets.pin(url)


def test_the_allow_setting_is_checked_at_start_up() -> None:
    assert parse_allow_list(" a.example , 10.0.0.0/8,[::1];fe80::/10 ") == (
        frozenset({"a.example"}),
        (ipaddress.ip_network("10.0.0.0/8"), ipaddress.ip_network("::1/128"), ipaddress.ip_network("fe80::/10")),
    )
    with pytest.raises(ValidationError, match="neither a host name nor an address range"):
        Settings(webhook_allow_targets="10.0.0.0/33")
    with pytest.raises(ValidationError, match="neither a host name nor an address range"):
        Settings(webhook_allow_targets="http://hooks.internal/")
