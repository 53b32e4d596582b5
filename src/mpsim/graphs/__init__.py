"""Graph topologies, batching and neighbour aggregation."""

from mpsim.graphs.batch import BatchedGraph as BatchedGraph
from mpsim.graphs.batch import batch_graph as batch_graph
from mpsim.graphs.batch import mean_aggregate as mean_aggregate
from mpsim.graphs.batch import sum_aggregate as sum_aggregate
from mpsim.graphs.topology import make_topology as make_topology
