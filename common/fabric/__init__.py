"""The fabric across sites: robots and operators meet through Zenoh routers.

keyexprs.py says where each message travels, session.py how a node reaches
its router (QUIC, mutual TLS), link.py the node's ``Sender`` and ``Receiver``
over it, certificates.py the small CA that names every roster member.
"""
