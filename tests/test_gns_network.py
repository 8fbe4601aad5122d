"""The message-passing convention, pinned with hand-computed values."""
import torch

from gns.network import EncodeProcessDecode, InteractionBlock

# 3 nodes, edges 0->1, 0->2, 1->2 (asymmetric: swapping senders and receivers changes everything).
SENDERS = torch.tensor([0, 0, 1])
RECEIVERS = torch.tensor([1, 2, 2])


def linear_block() -> InteractionBlock:
    """f_E(E, V_r, V_s) = E + 2 V_r + 3 V_s and f_V(V, sum) = V + 10 sum, latent size 1."""
    block = InteractionBlock(latent=1, hidden=1, hidden_layers=0, layer_norm=False)
    with torch.no_grad():
        block.edge_in.weight.fill_(1.0)
        block.edge_in.bias.zero_()
        block.receiver_in.weight.fill_(2.0)
        block.sender_in.weight.fill_(3.0)
        (node_linear,) = block.node_mlp
        node_linear.weight.copy_(torch.tensor([[1.0, 10.0]]))
        node_linear.bias.zero_()
    return block


def test_interaction_block_matches_hand_computation():
    nodes = torch.tensor([[1.0], [2.0], [4.0]])
    edges = torch.tensor([[0.5], [-1.0], [2.0]])
    new_nodes, [(new_edges, _, _)] = linear_block()(nodes, [(edges, SENDERS, RECEIVERS)])
    # messages m = E + 2 V_receiver + 3 V_sender: 0.5+4+3, -1+8+3, 2+8+6
    # sums at receivers: node 0 gets nothing, node 1 gets 7.5, node 2 gets 10 + 16 = 26
    # V' = V + (V + 10 sum); E' = E + m
    assert torch.equal(new_nodes, torch.tensor([[2.0], [79.0], [268.0]]))
    assert torch.equal(new_edges, torch.tensor([[8.0], [9.0], [18.0]]))


def test_swapping_senders_and_receivers_changes_the_result():
    nodes = torch.tensor([[1.0], [2.0], [4.0]])
    edges = torch.tensor([[0.5], [-1.0], [2.0]])
    block = linear_block()
    forward = block(nodes, [(edges, SENDERS, RECEIVERS)])[0]
    swapped = block(nodes, [(edges, RECEIVERS, SENDERS)])[0]
    assert not torch.allclose(forward, swapped)


def test_split_first_layer_equals_concatenated_mlp():
    torch.manual_seed(0)
    block = InteractionBlock(latent=4, hidden=5, hidden_layers=2)
    nodes, edges = torch.randn(3, 4), torch.randn(3, 4)
    w = torch.cat([block.edge_in.weight, block.receiver_in.weight, block.sender_in.weight], dim=1)
    first = torch.cat([edges, nodes[RECEIVERS], nodes[SENDERS]], dim=1) @ w.T + block.edge_in.bias
    messages = block.edge_rest(first)
    summed = torch.zeros_like(nodes).index_add_(0, RECEIVERS, messages)
    expected = nodes + block.node_mlp(torch.cat([nodes, summed], 1))
    got_nodes, [(got_edges, _, _)] = block(nodes, [(edges, SENDERS, RECEIVERS)])
    assert torch.allclose(got_nodes, expected, atol=1e-6)
    assert torch.allclose(got_edges, edges + messages, atol=1e-6)


def test_processor_applies_l_unshared_blocks_k_times_passing_updated_edges():
    torch.manual_seed(0)
    net = EncodeProcessDecode(node_in=2, edge_in=3, out_size=3, latent=8, hidden=8, hidden_layers=1,
                              message_passing_steps=2, processor_repeats=2)
    nodes, edges = torch.randn(3, 2), torch.randn(3, 3)
    v, e = net.node_encoder(nodes), net.edge_encoder(edges)
    for block in [net.blocks[0], net.blocks[1], net.blocks[0], net.blocks[1]]:
        v, [(e, _, _)] = block(v, [(e, SENDERS, RECEIVERS)])
    assert torch.allclose(net(nodes, edges, SENDERS, RECEIVERS), net.decoder(v), atol=1e-6)
    assert net.blocks[0].edge_in.weight.data_ptr() != net.blocks[1].edge_in.weight.data_ptr()


def test_encoders_end_in_layer_norm_and_decoder_does_not():
    net = EncodeProcessDecode(node_in=2, edge_in=3, out_size=3, latent=8, hidden=8, hidden_layers=2,
                              message_passing_steps=1)
    assert isinstance(net.node_encoder[-1], torch.nn.LayerNorm)
    assert isinstance(net.edge_encoder[-1], torch.nn.LayerNorm)
    assert isinstance(net.blocks[0].node_mlp[-1], torch.nn.LayerNorm)
    assert isinstance(net.decoder[-1], torch.nn.Linear)


def test_forward_flops_counts_every_linear_layer():
    net = EncodeProcessDecode(node_in=3, edge_in=1, out_size=3, latent=4, hidden=5, hidden_layers=1,
                              message_passing_steps=1, processor_repeats=3)
    n, e = 7, 11
    block = (2 * e * (4 * 5 + 5 * 4) + 2 * 2 * n * 4 * 5 + 2 * n * (8 * 5 + 5 * 4))
    expected = 2 * n * (3 * 5 + 5 * 4) + 2 * e * (1 * 5 + 5 * 4) + 3 * block + 2 * n * (4 * 5 + 5 * 3)
    assert net.forward_flops(n, e) == expected


def test_collision_edges_apply_the_node_parts_per_edge_as_the_mesh_edges_do_per_node():
    from gns.network import _edge_messages
    torch.manual_seed(0)
    net = EncodeProcessDecode(node_in=3, edge_in=1, out_size=3, latent=4, hidden=5, hidden_layers=1,
                              message_passing_steps=1, collision_edge_in=2).double()
    function = net.blocks[0].collision
    nodes, edges = torch.randn(9, 4, dtype=torch.float64), torch.randn(3, 4, dtype=torch.float64)
    senders, receivers = torch.tensor([0, 8, 8]), torch.tensor([5, 5, 1])
    per_edge = _edge_messages(function, nodes, edges, senders, receivers, per_node=False)
    per_node = _edge_messages(function, nodes, edges, senders, receivers, per_node=True)
    torch.testing.assert_close(per_edge, per_node, rtol=1e-12, atol=1e-12)
    # counted as run: the collision set's node parts once per collision edge, not per node
    n, e, c = 9, 5, 3
    encoder, block = 2 * 5 + 5 * 4, 3 * 4 * 5 + 5 * 4
    assert net.forward_flops(n, e, c) - net.forward_flops(n, e, 0) == 2 * c * (encoder + block)
