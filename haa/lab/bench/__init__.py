"""Benchmarks run by hand, beside `haactl bench` (haa.lab.experiments): A/B comparisons and profiles that write
bench-results/*.json (docs/results.md is generated from them). Each is a module run as
`python -m haa.lab.bench.<name> --help`:

* `carriers` — every commit-path goal per host-link carrier, runs alternating (bench-results/issue14-final.json)
* `hostlink_ab` — AP-1 on the gRPC and the TCP host link, alternating, with cluster CPU and frames per transaction
* `seq_ab` — the DDB all-writing load per carrier and sequencer batches in flight, optionally profiled (py-spy)
* `collapsed_top` — the top frames of py-spy's collapsed-stack profiles
* `hostd_oac_latency` — the message-hop cost inside a real haa-hostd cluster
* `transport_grpc_vs_tcp`, `transport_stream_vs_unary` — what one message costs per carrier and per gRPC style
* `metrics_cost` — what Prometheus metrics cost an idle local cluster
* `dashboard_latency` — committed change -> painted on the dashboard page, in headless Chromium
* `spawn_burst` — a burst of agent spawns on a fresh group: time until all are active, DDB latency meanwhile
"""
