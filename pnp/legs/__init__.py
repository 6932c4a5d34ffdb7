"""The learned low level on walking legs: the locomotion task the leg policy is trained on
(``locomotion``), the PnP worlds whose legs that policy drives at 50 Hz (``backend``), and
the arm's gravity feed-forward on the floating base (``arm_gravity``)."""
