"""``deepxpalm demo --fabric``: a fabric made for the run, as a lab would set one up.

A roster of one robot and one controller, their signing keys, the fabric's CA
and their certificates, and a router on a free UDP port of loopback, all in
the demo's 0700 directory. The robot connects to the router directly; the
operator reaches it through the link simulator's datagram mode, so its QUIC
connection crosses the scenario's delays, losses and outages.
"""

from __future__ import annotations

from pathlib import Path

from common.transport import free_loopback_ports
from deploy.scene import Scene


class DemoFabric:
    """Where the run's router listens, and what its config and the link simulator's are."""

    def __init__(self, router_config: Path, router_port: int, netsim_port: int) -> None:
        self.router_config = router_config
        self.router_udp = f"udp://127.0.0.1:{router_port}"
        self.netsim_udp = f"udp://127.0.0.1:{netsim_port}"


def use_fresh_fabric(scene: Scene, directory: Path, use_netsim: bool) -> DemoFabric:
    """A roster of one robot and one controller, their signing keys and certificates, and a
    router for this run only; the operator reaches the router through the link simulator.
    """
    from common.fabric.session import FabricConfig
    from common.signing import generate_key_files
    from deploy.keys_cli import fabric_certificates

    directory.mkdir(mode=0o700)
    directory.chmod(0o700)
    robot_link, op_link = scene.robot.link, scene.operator.link
    robot = robot_link.robot_name or "demo"
    robot_sign, robot_secret = generate_key_files(directory, "robot")
    op_sign, op_secret = generate_key_files(directory, "operator")
    roster = directory / "roster.toml"
    roster.write_text(
        '[[operator]]\nname = "operator"\nrole = "controller"\n'
        f'signing_key = "{op_sign.read_text().strip()}"\n\n[[robot]]\nname = "{robot}"\n'
    )
    certs = directory / "certs"
    fabric_certificates(roster, certs, "router", ("127.0.0.1",), False)
    router_port, netsim_port = free_loopback_ports(2, udp=True)
    robot_link.mode, robot_link.robot_name, robot_link.roster_file = "fabric", robot, roster
    robot_link.signing_key_file = robot_secret
    robot_link.fabric = FabricConfig(
        router_endpoint=f"quic/127.0.0.1:{router_port}", cert_dir=certs
    )
    op_link.mode, op_link.robot_name, op_link.request_control = "fabric", robot, True
    op_link.signing_key_file, op_link.robot_key_file = op_secret, robot_sign
    op_port = netsim_port if use_netsim else router_port
    op_link.fabric = FabricConfig(
        router_endpoint=f"quic/127.0.0.1:{op_port}", cert_dir=certs, name="operator"
    )
    router_config = directory / "router.toml"
    router_config.write_text(
        f'[router]\nlisten_endpoint = "quic/127.0.0.1:{router_port}"\n'
        f'roster_file = "{roster}"\ncert_dir = "{certs}"\n'
    )
    return DemoFabric(router_config, router_port, netsim_port)
