"""Toss a cube with the zoo's real_cubes model (real ContactNets cube tosses; units: cube half-widths)."""
import gns

model = gns.load("real_cubes")   # a zoo name (`gns models`), a run folder or a .pt file; device="cuda"
out = model.rollout(shapes=["cube"], scales=2.0,  # the cube spans 2 half-widths
                    positions=[[0.0, 0.0, 3.0]], quaternions=[[1.0, 0.0, 0.0, 0.0]],  # w x y z
                    velocities=[[10.0, 0.0, 5.0]], angular_velocities=[[0.0, 4.0, 0.0]], steps=30)
for k in range(0, 31, 5):
    x, y, z = out.positions[k, 0].tolist()
    print(f"t={k * model.dt:.2f} s  x={x:6.2f}  y={y:6.2f}  z={z:5.2f}")
