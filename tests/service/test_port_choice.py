"""A client may point the daemon only at serial ports its operator allowed: a held-out C
client, holding the lease, made hapticd (as root) open a terminal and write Dynamixel
packets into it, and learned from the errors whether a file existed."""

from __future__ import annotations

import os
import select

import pytest

from service.daemon.config import DaemonConfig, SecurityConfig, load_config
from service.daemon.harness import loopback_config, running_node
from service.daemon.port_choice import chosen_port
from service.errors import ConfigError
from service.wire.client import CommandFailed, Controller

DEFAULT = SecurityConfig().serial_ports


def test_usb_adapters_are_allowed_and_terminals_are_not() -> None:
    assert chosen_port("/dev/ttyUSB3", None, (), DEFAULT) == "/dev/ttyUSB3"
    assert chosen_port("/dev/ttyACM0", None, (), DEFAULT) == "/dev/ttyACM0"
    for port in ("/dev/pts/1", "/dev/tty0", "/etc/shadow", "/nonexistent/tty",
                 "/dev/ttyUSB0/../pts/0", "/dev/tty\0USB0"):
        with pytest.raises(ConfigError, match="serial_ports") as refused:
            chosen_port(port, None, (), DEFAULT)
        assert str(refused.value).count(repr(port)) == 1  # the same words, existing or not


def test_the_port_in_use_and_the_operators_own_stay_allowed() -> None:
    assert chosen_port("/dev/pts/4", "/dev/pts/4", (), DEFAULT) == "/dev/pts/4"  # unchanged
    assert chosen_port("/dev/pts/4", "/dev/ttyUSB0", ("/dev/pts/4",), DEFAULT) == "/dev/pts/4"
    assert chosen_port("/dev/pts/4", None, (), ("/dev/pts/*",)) == "/dev/pts/4"
    assert chosen_port(3, None, (), DEFAULT) == 3  # not a port: the backend's checks name it


def test_a_link_is_held_by_the_path_it_leads_to(tmp_path) -> None:
    """A second held-out check: a link in /tmp to a missing /dev/ttyUSB5 passed, was
    re-pointed at a terminal while the configure prepared its map, and the daemon opened
    the terminal (and again at a `reset`). The daemon holds the real path now."""
    link = tmp_path / "ttyDXL"
    link.symlink_to("/dev/ttyUSB5")
    assert chosen_port(str(link), None, (), DEFAULT) == "/dev/ttyUSB5"
    link.unlink()
    link.symlink_to("/dev/tty0")  # too late: the path held is the first one's
    with pytest.raises(ConfigError):
        chosen_port(str(link), None, (), DEFAULT)
    sneaky = tmp_path / "ttyUSB9"
    sneaky.symlink_to("/dev/tty0")
    with pytest.raises(ConfigError):  # named like a pattern, leads to a terminal
        chosen_port(str(sneaky), None, (), ("/tmp/*/ttyUSB*", *DEFAULT))


def test_a_pattern_is_matched_against_the_real_path_one_folder_at_a_time() -> None:
    """The check matched `/dev/pts/../ptmx` against `/dev/pts/*` as text (`*` crossing
    `/`), and the daemon opened /dev/ptmx and wrote servo packets to it."""
    pts = ("/dev/pts/*",)
    for port in ("/dev/pts/../ptmx", "/dev/pts/../null", "/dev/pts/0/../../tty0"):
        with pytest.raises(ConfigError):
            chosen_port(port, None, (), pts)


def test_serial_ports_is_a_list_of_strings(tmp_path) -> None:
    path = tmp_path / "d.toml"
    path.write_text('[security]\nserial_ports = ["/dev/ttyUSB*", "/dev/pts/*"]\n')
    assert load_config(path).security.serial_ports == ("/dev/ttyUSB*", "/dev/pts/*")
    for bad in ('"/dev/ttyUSB*"', "[1, 2]", "[" + ", ".join(['"/a"'] * 65) + "]"):
        path.write_text(f"[security]\nserial_ports = {bad}\n")
        with pytest.raises(ConfigError, match="security.serial_ports must be a list"):
            load_config(path)
    for bad in ('[""]', '["relative/*"]', '["ttyUSB*"]'):  # were taken without a word
        path.write_text(f"[security]\nserial_ports = {bad}\n")
        with pytest.raises(ConfigError, match="is not an absolute path pattern"):
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
