"""Emulated CiA 402 servo drives on a python-can bus (object dictionary, drive, drive set, CLI).

Import the parts you need (``sim_hardware.canopen.network.DriveSet``, ``...drive.EmulatedDrive``,
``...od.build_od``); this package module itself stays import-light for the CLI.
"""
