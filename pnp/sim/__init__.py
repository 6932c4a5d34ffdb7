"""The simulated world: the robot, the box, the scene and its randomised layout, the MuJoCo
worlds stepped together (``physics``), the MuJoCo backend of the env (``backend``), the
low-level executors that turn 10 Hz commands into actuator controls, the arm's inverse
kinematics (``arm_ik``, ``arm_closed_form``) and offscreen rendering."""
