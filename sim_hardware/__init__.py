"""Emulated hardware that speaks the real protocols: CiA 402 drives, Dynamixel servos, a head, a tracker."""
