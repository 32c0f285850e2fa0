"""The distributed database (thesis §4.2.2, §6.1.3; docs/ddb.md): a replicated state machine every host holds.

* `ddb.py`: `Ddb`, one replica: applies batches of operations in the OAC's total order, watchers, the mirror
  ring, snapshots; what `apply` reports;
* `objects.py`: the bounds, the object types (blob, json, list, counter, log) and `DdbObject`;
* `ops.py`: the client side: op builders (`put`, `delete`, `append`, `cas`, `add`, `log_append`, `log_trim`),
  `encode_batch`, the checks a host runs before proposing;
* `agenttable.py`: the replicated agent table, the thesis' "DDB.agents" (Alg. 5-8 read and write it): which
  agents exist, who owns each, their state, backups and queues.

Code inside haa imports from the defining module (`haa.core.ddb.ops`, ...); this file re-exports nothing.
"""
