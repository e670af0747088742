"""The robot PC's node: tactile pads, gripper, arm, perception, rendering."""
