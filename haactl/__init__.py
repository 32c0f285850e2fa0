"""haactl: the operator command line of HAA."""
