"""HAA (Host, Avatar, Agent): a framework for robot teams formed at run time from the hosts, avatars and
agents at hand. See DESIGN.md and the thesis (Chapter 4, Appendix II) for the algorithms."""

__version__ = "0.1.0"
