"""A client may point the daemon only at serial ports its operator allowed: a held-out C
client, holding the lease, made hapticd (as root) open a terminal and write Dynamixel
packets into it, and learned from the errors whether a file existed."""

from __future__ import annotations

import os
import select

import pytest

from service.daemon.config import DaemonConfig, SecurityConfig, load_config
from service.daemon.harness import loopback_config, running_node
from service.daemon.port_choice import check_port_choice
from service.errors import ConfigError
from service.wire.client import CommandFailed, Controller

DEFAULT = SecurityConfig().serial_ports


def test_usb_adapters_are_allowed_and_terminals_are_not() -> None:
    check_port_choice("/dev/ttyUSB3", None, (), DEFAULT)
    check_port_choice("/dev/ttyACM0", None, (), DEFAULT)
    for port in ("/dev/pts/1", "/dev/tty0", "/etc/shadow", "/nonexistent/tty"):
        with pytest.raises(ConfigError, match="serial_ports") as refused:
            check_port_choice(port, None, (), DEFAULT)
        assert str(refused.value).count(port) == 1  # the same words, existing or not


def test_the_port_in_use_and_the_operators_own_stay_allowed(tmp_path) -> None:
    check_port_choice("/dev/pts/4", "/dev/pts/4", (), DEFAULT)  # unchanged
    check_port_choice("/dev/pts/4", "/dev/ttyUSB0", ("/dev/pts/4",), DEFAULT)
    check_port_choice("/dev/pts/4", None, (), ("/dev/pts/*",))
    check_port_choice(3, None, (), DEFAULT)  # not a port: the backend's checks name it


def test_a_link_is_judged_by_its_name_or_where_it_leads(tmp_path) -> None:
    link = tmp_path / "ttyDXL"
    link.symlink_to("/dev/ttyUSB0")
    check_port_choice(str(link), None, (), DEFAULT)  # leads to an adapter
    sneaky = tmp_path / "ttyUSB9"
    sneaky.symlink_to("/dev/tty0")
    with pytest.raises(ConfigError):  # named like none of the patterns, leads to a terminal
        check_port_choice(str(sneaky), None, (), DEFAULT)


def test_serial_ports_is_a_list_of_strings(tmp_path) -> None:
    path = tmp_path / "d.toml"
    path.write_text('[security]\nserial_ports = ["/dev/ttyUSB*", "/dev/pts/*"]\n')
    assert load_config(path).security.serial_ports == ("/dev/ttyUSB*", "/dev/pts/*")
    for bad in ('"/dev/ttyUSB*"', "[1, 2]", "[" + ", ".join(['"a"'] * 65) + "]"):
        path.write_text(f"[security]\nserial_ports = {bad}\n")
        with pytest.raises(ConfigError, match="security.serial_ports must be a list"):
            load_config(path)
    assert DaemonConfig().security.serial_ports == DEFAULT


def test_a_client_cannot_make_the_daemon_write_into_a_terminal() -> None:
    main, other = os.openpty()  # a terminal of ours: what hapticd writes there, we read
    terminal = os.ttyname(other)
    try:
        with running_node(loopback_config()) as node, \
                Controller(node.endpoints["cmd"], timeout_s=30.0) as ctl:
            before = ctl.call("get_config")
            replies = []
            for port in (terminal, "/nonexistent/tty"):
                with pytest.raises(CommandFailed) as refused:
                    ctl.call("configure", changes={"backend": {
                        "name": "dynamixel", "options": {"port": port, "hand": "planar"}}})
                assert refused.value.code == "bad_config"
                replies.append(str(refused.value).replace(port, "PORT"))
            assert replies[0] == replies[1]  # nothing told of which exists
            assert ctl.call("get_config") == before
            assert ctl.call("status")["state"] == "inactive"
        assert select.select([main], [], [], 0)[0] == []  # not a byte was written
    finally:
        os.close(main)
        os.close(other)
