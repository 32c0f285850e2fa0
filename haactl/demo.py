"""`haactl demo`: the main job on a local cluster (until missions exist, an OAC workout).

Starts N real `haa-hostd` processes on loopback, waits until every host trusts every other, then runs
`--transactions` OAC transactions from every host concurrently (each proposer keeps `--concurrency`
proposals in flight; every transaction goes to every live host). Half way through it kills one host with
SIGKILL; from then on transactions go to the survivors only, and the ones in flight when it died are
decided by the survivors (commit or abort, the same everywhere). At the end it prints, per host, how many
transactions it delivered and the hash of its delivered sequence — identical on every survivor — plus
latency percentiles, messages per transaction and how long the survivors took to suspect the dead host.
"""

from __future__ import annotations

import contextlib
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import grpc
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from haactl.ap1 import oac_messages_sent, percentile
from haactl.local import LocalCluster, wait_for

console = Console()


class Workload:
    """Proposers on every host; participants switch to the survivors once the victim is killed."""

    def __init__(self, cluster: LocalCluster, names: list[str], victim: str, total: int, concurrency: int) -> None:
        self.cluster = cluster
        self.names = names
        self.victim = victim
        self.total = total
        self.concurrency = concurrency
        self.lock = threading.Lock()
        self.live = list(names)
        self.next = 0
        self.done = 0
        self.committed = 0
        self.aborted = 0
        self.lost = 0  # proposals on the victim when it died (no answer)
        self.p2d: list[float] = []
        self.killed = threading.Event()

    def take(self) -> tuple[int, list[str]] | None:
        with self.lock:
            if self.next >= self.total:
                return None
            i = self.next
            self.next += 1
            return i, list(self.live)

    def proposer(self, host: str) -> None:
        client = self.cluster[host].client
        while True:
            if host not in self.live:
                return
            job = self.take()
            if job is None:
                return
            i, parts = job
            try:
                reply = client.propose(f"demo-{i}".encode(), parts, wait=True, timeout=30)
                with self.lock:
                    self.done += 1
                    if reply.committed:
                        self.committed += 1
                        self.p2d.append(reply.propose_to_decide)
                    else:
                        self.aborted += 1
            except grpc.RpcError:
                with self.lock:
                    self.done += 1
                    if host == self.victim and self.killed.is_set():
                        self.lost += 1
                    else:
                        self.aborted += 1

    def kill(self) -> float:
        with self.lock:
            self.live.remove(self.victim)
        self.killed.set()
        t = time.monotonic()
        self.cluster[self.victim].kill9()
        return t


def run_demo(hosts: int, transactions: int, concurrency: int, root: Path) -> dict[str, Any]:
    names = [f"h{i + 1}" for i in range(hosts)]
    victim = names[len(names) // 2]
    with LocalCluster(names, root) as cluster:
        console.print(f"[bold]HAA demo[/bold]: {hosts} haa-hostd processes on loopback, data in {root}")
        cluster.start()
        with console.status("waiting for every host to trust every other ..."):
            t0 = time.monotonic()
            cluster.wait_trusted(timeout=60)
        console.print(f"cluster formed in {time.monotonic() - t0:.2f} s")
        msgs0 = oac_messages_sent(cluster, names)
        wl = Workload(cluster, names, victim, transactions, concurrency)
        killed_at = 0.0
        victim_msgs = 0
        start = time.monotonic()
        with (
            Progress(
                TextColumn("OAC transactions"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[note]}"),
                TimeElapsedColumn(),
                console=console,
            ) as progress,
            ThreadPoolExecutor(max_workers=hosts * concurrency) as pool,
        ):
            task = progress.add_task("tx", total=transactions, note="")
            futures = [pool.submit(wl.proposer, h) for h in names for _ in range(concurrency)]
            while not all(f.done() for f in futures):
                progress.update(task, completed=wl.done)
                if not killed_at and wl.done >= transactions // 2:
                    victim_msgs = sum(
                        v
                        for k, v in cluster[victim].status().counters.values.items()
                        if k.startswith("tx_msgs.oac_")
                    )
                    killed_at = wl.kill()
                    progress.update(task, note=f"[red]killed {victim} (SIGKILL)[/red]")
                time.sleep(0.05)
            for f in futures:
                f.result()
            progress.update(task, completed=wl.done)
        elapsed = time.monotonic() - start
        survivors = [n for n in names if n != victim]
        # how long the survivors took to suspect the dead host (from their JSON-lines logs)
        detect = []
        for n in survivors:
            for ev in cluster[n].log_events():
                f = ev.get("fields", {})
                if ev.get("event") == "suspicion" and f.get("peer") == victim and f.get("suspected"):
                    detect.append(ev["ts"])
        wait_for(
            lambda: all(cluster[n].status().active_transactions == 0 for n in survivors), 15, "survivors to settle"
        )
        statuses = {n: cluster[n].status() for n in survivors}
        msgs = oac_messages_sent(cluster, survivors) + victim_msgs - msgs0
        d2d: list[float] = []
        for n in survivors:
            d2d.extend(cluster[n].client.latencies().decide_to_deliver)
        kill_wall = time.time() - (time.monotonic() - killed_at)
        detection = [t - kill_wall for t in detect if t >= kill_wall - 0.01]
        return {
            "names": names,
            "victim": victim,
            "survivors": survivors,
            "statuses": statuses,
            "workload": wl,
            "elapsed": elapsed,
            "messages": msgs,
            "d2d": d2d,
            "detection": detection,
        }


def report(r: dict[str, Any]) -> bool:
    wl: Workload = r["workload"]
    table = Table(title="delivered sequence per host")
    table.add_column("host")
    table.add_column("delivered", justify="right")
    table.add_column("hash of the delivered sequence (sha256 chain, first 32 hex)")
    hashes = set()
    for n in r["names"]:
        if n == r["victim"]:
            table.add_row(n, "-", "[red]killed half way[/red]")
            continue
        st = r["statuses"][n]
        hashes.add(st.delivered_hash)
        table.add_row(n, str(st.delivered), st.delivered_hash[:32])
    console.print(table)
    same = len(hashes) == 1
    console.print(
        ("[green]identical on every survivor[/green]" if same else "[red]SURVIVORS DISAGREE[/red]")
        + f" ({len(r['survivors'])} survivors)"
    )
    p2d, d2d = wl.p2d, r["d2d"]
    lat = Table(title="latency (ms)")
    for col in ("", "p50", "p90", "p99", "samples"):
        lat.add_column(col, justify="right")
    lat.add_row("propose → decide", *(f"{percentile(p2d, q) * 1e3:.2f}" for q in (50, 90, 99)), str(len(p2d)))
    lat.add_row("decide → deliver", *(f"{percentile(d2d, q) * 1e3:.2f}" for q in (50, 90, 99)), str(len(d2d)))
    console.print(lat)
    n_tx = wl.done
    console.print(
        f"{wl.total} transactions in {r['elapsed']:.1f} s ({wl.done / r['elapsed']:.0f}/s): {wl.committed} committed, "
        f"{wl.aborted} aborted, {wl.lost} lost with the killed host's proposer"
    )
    console.print(
        f"OAC messages per transaction: {r['messages'] / max(n_tx, 1):.1f} "
        f"(failure-free n²+4n−6: {5 * 5 + 4 * 5 - 6} for 5 participants, {4 * 4 + 4 * 4 - 6} for 4)"
    )
    if r["detection"]:
        console.print(
            f"survivors suspected {r['victim']} {min(r['detection']):.2f}-{max(r['detection']):.2f} s after the kill"
        )
    return same


def demo(
    hosts: int = typer.Option(5, "--hosts", min=3, max=16),
    transactions: int = typer.Option(1000, "--transactions", "-n", min=10),
    concurrency: int = typer.Option(2, "--concurrency", min=1, max=16, help="in-flight proposals per host"),
    data_dir: Path | None = typer.Option(None, "--data-dir", help="keep the hosts' logs here"),
) -> None:
    """Run the main job on a local cluster: concurrent OAC transactions, one host killed half way."""
    with contextlib.ExitStack() as stack:
        root = data_dir or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="haa-demo-")))
        r = run_demo(hosts, transactions, concurrency, root)
        if not report(r):
            raise typer.Exit(1)
