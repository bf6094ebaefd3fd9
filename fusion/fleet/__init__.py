"""Many flights on a dask.distributed cluster: `run_batch` (fusion batch), the fleet summary.

batch.py     run_batch, BatchConfig, connect: the driver and the cluster
tasks.py     one flight's task graph, wrapping fusion.pipeline's stage functions
parts.py     the task results handed to the report task as files (OUT/.parts)
flights.py   flight lists, output names, the fleet state file OUT/fleet.json
summary.py   OUT/fleet.csv and OUT/fleet.md with plots
"""

from fusion.fleet.batch import BatchConfig, BatchResult, run_batch
from fusion.fleet.flights import FlightRecord, FlightStatus

__all__ = ["BatchConfig", "BatchResult", "FlightRecord", "FlightStatus", "run_batch"]
