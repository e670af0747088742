"""udev rules giving the serial devices stable names, shipped as package data."""
