"""Example configs for the two machines (robot.toml, operator.toml), shipped as package data.

A package only so that an installed wheel carries them too: copy one to
/etc/deepxpalm/ and edit the lines marked LAB.
"""
