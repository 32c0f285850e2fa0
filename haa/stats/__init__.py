"""Statistics of a cluster: each host's sampler (sampler), bundles (bundle, collect), the cluster summary
(summary, phases) and the HTML report (report, figures). docs/stats.md."""
