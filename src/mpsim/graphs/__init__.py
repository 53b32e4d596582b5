"""Graph topologies, batching and neighbour aggregation, particle graphs (full, kNN, quadtree hierarchy)."""

from mpsim.graphs.batch import BatchedGraph as BatchedGraph
from mpsim.graphs.batch import batch_graph as batch_graph
from mpsim.graphs.batch import mean_aggregate as mean_aggregate
from mpsim.graphs.batch import sum_aggregate as sum_aggregate
from mpsim.graphs.hierarchy import build_hierarchy as build_hierarchy
from mpsim.graphs.knn import full_graph as full_graph
from mpsim.graphs.knn import knn_graph as knn_graph
from mpsim.graphs.topology import make_topology as make_topology
