"""Statistics of a cluster: each host's sampler (sampler), bundles (bundle, collect), the cluster summary
(summary, phases), one run directory read (run) and the HTML report (report, figures). docs/stats.md."""
