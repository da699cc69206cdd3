"""The handlers of the `qnav` verbs: each turns parsed options into typed settings and calls
the package that does the work (the packages take no argparse)."""
