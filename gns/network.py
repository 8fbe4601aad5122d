"""Encode-process-decode graph network on an already built, normalised graph. Imports only torch.

Message passing convention (pinned by tests/test_gns_network.py):
- An edge k goes from node s = senders[k] to node r = receivers[k]. In the paper's notation
  E_ij with i = r (the node that is updated) and j = s (its neighbour).
- Edge update: m_k = f_E(E_k, V_r, V_s), inputs concatenated in that order.
- Node update: V'_r = V_r + f_V(V_r, sum_{k: receivers[k] = r} m_k). A node sums the new
  messages m_k, i.e. the edge update *before* the edge residual is added, as DeepMind's
  InteractionNetwork (graph_nets / jraph) does.
- Edge residual: E'_k = E_k + m_k; the next block sees E'.
- The processor holds L blocks with unshared weights and applies the sequence K times.
- Optional second edge set (collision edges between objects, as MeshGraphNets' world edges):
  its own encoder and per-block edge function c_k = f_C(C_k, V_r, V_s); then
  V'_r = V_r + f_V(V_r, sum mesh messages, sum collision messages) and C'_k = C_k + c_k.
  A network built without it (collision_edge_in = 0) has none of these parameters.
"""
from __future__ import annotations

import torch
from torch import nn


class MLP(nn.Sequential):
    """`hidden_layers` ReLU layers of width `hidden`, a linear output, optionally a LayerNorm."""

    def __init__(self, in_size: int, hidden: int, hidden_layers: int, out_size: int, layer_norm: bool):
        sizes = [in_size] + [hidden] * hidden_layers
        layers: list[nn.Module] = []
        for a, b in zip(sizes[:-1], sizes[1:]):
            layers += [nn.Linear(a, b), nn.ReLU()]
        layers.append(nn.Linear(sizes[-1], out_size))
        if layer_norm:
            layers.append(nn.LayerNorm(out_size))
        super().__init__(*layers)


def _add_edge_function(module: nn.Module, latent: int, hidden: int, hidden_layers: int, layer_norm: bool) -> None:
    """Give `module` the layers of f_E(E, V_r, V_s): an MLP whose first layer is split into
    edge_in (on E), receiver_in (on V_r) and sender_in (on V_s), then edge_rest."""
    first = hidden if hidden_layers > 0 else latent
    module.edge_in = nn.Linear(latent, first)
    module.receiver_in = nn.Linear(latent, first, bias=False)
    module.sender_in = nn.Linear(latent, first, bias=False)
    rest: list[nn.Module] = []
    if hidden_layers > 0:
        rest.append(nn.ReLU())
        rest.extend(MLP(hidden, hidden, hidden_layers - 1, latent, layer_norm))
    elif layer_norm:
        rest.append(nn.LayerNorm(latent))
    module.edge_rest = nn.Sequential(*rest)


def _edge_messages(module: nn.Module, nodes, edges, senders, receivers) -> torch.Tensor:
    # The node parts of the first layer are applied once per node, then gathered per edge:
    # equal to the concatenated form but O(N) instead of O(E). index_select is the gather
    # x[idx]; its backward (index_add_) is about twice as fast on CPU.
    projected = (module.edge_in(edges) + module.receiver_in(nodes).index_select(0, receivers)
                 + module.sender_in(nodes).index_select(0, senders))
    return module.edge_rest(projected)


class InteractionBlock(nn.Module):
    """One message-passing update with residuals on nodes and edges (see the module docstring).

    The first layer of f_E acts on [E, V_r, V_s]; its node parts are applied once per node and
    then gathered per edge, which equals the concatenated form but costs O(N) instead of O(E).
    """

    def __init__(self, latent: int, hidden: int, hidden_layers: int, layer_norm: bool = True,
                 collisions: bool = False):
        super().__init__()
        _add_edge_function(self, latent, hidden, hidden_layers, layer_norm)
        self.collision = EdgeFunction(latent, hidden, hidden_layers, layer_norm) if collisions else None
        self.node_mlp = MLP((3 if collisions else 2) * latent, hidden, hidden_layers, latent, layer_norm)

    def forward(self, nodes: torch.Tensor, edges: torch.Tensor, senders: torch.Tensor,
                receivers: torch.Tensor, collision: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None):
        """nodes (N, D), edges (E, D), senders/receivers (E,) -> new nodes (N, D), edges (E, D).

        With collision = (edges (C, D), senders (C,), receivers (C,)) (a block built with
        collisions needs it) -> new nodes, edges and collision edges (C, D).
        """
        messages = _edge_messages(self, nodes, edges, senders, receivers)
        summed = torch.zeros_like(nodes).index_add_(0, receivers, messages)
        if self.collision is None:
            new_nodes = nodes + self.node_mlp(torch.cat([nodes, summed], dim=-1))
            return new_nodes, edges + messages
        c_edges, c_senders, c_receivers = collision
        c_messages = self.collision(nodes, c_edges, c_senders, c_receivers)
        c_summed = torch.zeros_like(nodes).index_add_(0, c_receivers, c_messages)
        new_nodes = nodes + self.node_mlp(torch.cat([nodes, summed, c_summed], dim=-1))
        return new_nodes, edges + messages, c_edges + c_messages


class EdgeFunction(nn.Module):
    """f_E(E, V_r, V_s) of a further edge set, first layer split per node as in InteractionBlock."""

    def __init__(self, latent: int, hidden: int, hidden_layers: int, layer_norm: bool = True):
        super().__init__()
        _add_edge_function(self, latent, hidden, hidden_layers, layer_norm)

    def forward(self, nodes, edges, senders, receivers) -> torch.Tensor:
        return _edge_messages(self, nodes, edges, senders, receivers)


class EncodeProcessDecode(nn.Module):
    """Node and edge encoders (MLP + LayerNorm), L x K interaction blocks, node decoder (MLP)."""

    def __init__(self, node_in: int, edge_in: int, out_size: int, latent: int = 128, hidden: int = 128,
                 hidden_layers: int = 2, message_passing_steps: int = 10, processor_repeats: int = 1,
                 collision_edge_in: int = 0):
        super().__init__()
        self.processor_repeats = processor_repeats
        self.node_encoder = MLP(node_in, hidden, hidden_layers, latent, layer_norm=True)
        self.edge_encoder = MLP(edge_in, hidden, hidden_layers, latent, layer_norm=True)
        collisions = collision_edge_in > 0
        if collisions:
            self.collision_encoder = MLP(collision_edge_in, hidden, hidden_layers, latent, layer_norm=True)
        self.blocks = nn.ModuleList(InteractionBlock(latent, hidden, hidden_layers, collisions=collisions)
                                    for _ in range(message_passing_steps))
        self.decoder = MLP(latent, hidden, hidden_layers, out_size, layer_norm=False)

    @property
    def collisions(self) -> bool:
        return hasattr(self, "collision_encoder")

    def forward(self, nodes: torch.Tensor, edges: torch.Tensor, senders: torch.Tensor,
                receivers: torch.Tensor, collision_edges: torch.Tensor | None = None,
                collision_senders: torch.Tensor | None = None,
                collision_receivers: torch.Tensor | None = None) -> torch.Tensor:
        """nodes (N, node_in), edges (E, edge_in), senders/receivers (E,) int64 -> (N, out_size).

        A network with collisions also takes collision_edges (C, collision_edge_in) and their
        senders/receivers (C,); C may be 0.
        """
        v = self.node_encoder(nodes)
        e = self.edge_encoder(edges)
        if not self.collisions:
            for _ in range(self.processor_repeats):
                for block in self.blocks:
                    v, e = block(v, e, senders, receivers)
            return self.decoder(v)
        c = self.collision_encoder(collision_edges)
        for _ in range(self.processor_repeats):
            for block in self.blocks:
                v, e, c = block(v, e, senders, receivers, (c, collision_senders, collision_receivers))
        return self.decoder(v)

    def forward_flops(self, num_nodes: int, num_edges: int, num_collision_edges: int = 0) -> int:
        """Multiply-add FLOPs (2 per MAC) of all Linear layers in one forward pass."""
        def linear_flops(module: nn.Module, rows: int) -> int:
            return sum(2 * rows * m.in_features * m.out_features
                       for m in module.modules() if isinstance(m, nn.Linear))

        block_flops = sum(
            linear_flops(b.edge_in, num_edges) + linear_flops(b.edge_rest, num_edges)
            + linear_flops(b.receiver_in, num_nodes) + linear_flops(b.sender_in, num_nodes)
            + linear_flops(b.node_mlp, num_nodes) for b in self.blocks)
        if self.collisions:
            block_flops += sum(
                linear_flops(b.collision.edge_in, num_collision_edges) + linear_flops(b.collision.edge_rest, num_collision_edges)
                + linear_flops(b.collision.receiver_in, num_nodes) + linear_flops(b.collision.sender_in, num_nodes)
                for b in self.blocks)
        encoders = linear_flops(self.node_encoder, num_nodes) + linear_flops(self.edge_encoder, num_edges)
        if self.collisions:
            encoders += linear_flops(self.collision_encoder, num_collision_edges)
        return (encoders
                + self.processor_repeats * block_flops + linear_flops(self.decoder, num_nodes))
