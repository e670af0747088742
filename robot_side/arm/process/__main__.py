"""``python -m robot_side.arm.process``: the arm process (started by the robot node)."""

from robot_side.arm.process.child import main

if __name__ == "__main__":
    main()
