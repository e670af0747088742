"""Built-in link scenarios, one TOML file each (a package so they ship as data)."""
