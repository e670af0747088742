"""What every device shares: its lifecycle (lifecycle.py), preflight checks, a pty wire."""
