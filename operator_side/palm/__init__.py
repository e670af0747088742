"""The palm: from a 3x3 stimulus to LinkGlide's servo goals, and off the palm again.

- ``contact``: each stimulus row -> a contact point on the palm;
- ``linkage``: one five-bar linkage's geometry and inverse kinematics, in
  plain numbers; ``linkglide``: the same over arrays;
- ``renderer``: ``LinkGlideRenderer``, stimulus -> contact points -> IK ->
  servo counts, rate limited; ``renderer_config``: its settings and the
  retract pose;
- ``lift``: every linkage off the palm from a process that is not the node
  (``deepxpalm palm lift``); ``guard``: that lift started ahead of time,
  beside the node (``deepxpalm palm guard``).

Importing this package imports nothing: ``palm lift`` must start without
NumPy.
"""
