"""The operator PC's node: stimulus to contact points to LinkGlide servos.

Never imports torch (checked by tests): this machine only renders.
"""
