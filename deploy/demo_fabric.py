"""``deepxpalm demo --fabric``: a fabric made for the run, as a lab would set one up.

A roster of one robot and one controller, their signing keys, the fabric's CA
and their certificates, and a router on loopback, all in the demo's 0700
directory. The router binds a free UDP port and says which in its
``READY=1``; the robot connects to it directly; the operator reaches it
through the link simulator's datagram mode, so its QUIC connection crosses
the scenario's delays, losses and outages.
"""

from __future__ import annotations

from pathlib import Path

from deploy.scene import Scene

#: the router's listener before it is up: a free port of its own choosing
ANY_PORT = "quic/127.0.0.1:0"


class DemoFabric:
    """The run's router config, and the nodes pointed at the router once it is up."""

    def __init__(self, router_config: Path, roster: Path, certs: Path) -> None:
        self.router_config = router_config
        self.roster = roster
        self.certs = certs
        self.listen = ANY_PORT
        self.write_router_config()

    def write_router_config(self) -> None:
        self.router_config.write_text(
            f'[router]\nlisten_endpoint = "{self.listen}"\n'
            f'roster_file = "{self.roster}"\ncert_dir = "{self.certs}"\n'
        )

    def router_up(self, scene: Scene, listen: str, use_netsim: bool) -> None:
        """The router listens at ``listen`` (its READY=1): the robot connects there, and the
        operator too unless the link simulator stands between; a restarted router binds it
        again."""
        self.listen = listen
        self.write_router_config()
        scene.robot.link.fabric.router_endpoint = listen
        if not use_netsim:
            scene.operator.link.fabric.router_endpoint = listen

    @property
    def router_udp(self) -> str:
        """The router's UDP address, for the link simulator's datagram mode."""
        return "udp://" + self.listen.removeprefix("quic/")


def use_fresh_fabric(scene: Scene, directory: Path) -> DemoFabric:
    """A roster of one robot and one controller, their signing keys and certificates, and a
    router config for this run only; the endpoints are set once the router (and the link
    simulator) said where they listen.
    """
    from common.fabric.session import FabricConfig
    from common.wire.signing import generate_key_files
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
    robot_link.mode, robot_link.robot_name, robot_link.roster_file = "fabric", robot, roster
    robot_link.signing_key_file = robot_secret
    robot_link.fabric = FabricConfig(router_endpoint=ANY_PORT, cert_dir=certs)
    op_link.mode, op_link.robot_name, op_link.request_control = "fabric", robot, True
    op_link.signing_key_file, op_link.robot_key_file = op_secret, robot_sign
    op_link.fabric = FabricConfig(router_endpoint=ANY_PORT, cert_dir=certs, name="operator")
    return DemoFabric(directory / "router.toml", roster, certs)
