"""Running the nodes: the ``deepxpalm`` command, scenes, the demo, deployment files."""
