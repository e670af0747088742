"""The tactile contract both nodes share, and what is made of a frame.

contract.py: frames, forces, patterns, grip levels (scale.py: the force scale
without NumPy); stimulus.py: a frame to the 3x3 stimulus; synthetic.py and
synthetic_params.py: synthetic grasps for the classifier, simulators and tests.
"""
