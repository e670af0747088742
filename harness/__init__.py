"""The test harness: the benchmark, the fault matrix, the fleet, the soak, a scripted
operator and a headless browser.

It sits above the product: it may import every product package (common, the three
sides, deploy); nothing in the product imports it. Its commands (`deepxpalm bench`,
`deepxpalm soak`) reach the `deepxpalm` command through the `deepxpalm.commands`
entry-point group (pyproject.toml).
"""
