"""systemd units for both nodes, shipped as package data (docs/deploy.md installs them)."""
