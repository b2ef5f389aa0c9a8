"""Is the training gradient of a NeuralFMU right? Autograd against central differences.

One element of --span seconds from a point --t0 seconds into a run of the plain FMU (its FMU state
captured there, as the training's element starts are), an ANN acting on one derivative channel with
small random weights (as after a few training steps), and a loss like the training's: the mean over
the recorded signals of MSE(hybrid - plain FMU) / variance. For a few random unit directions d in
the network's parameters, and for each parameter tensor's own direction, it prints the slope
autograd gives (g . d) against the central difference (L(theta + s d) - L(theta - s d)) / 2s, for
steps s from 1e-2 to 1e-6 of |theta|. A right gradient agrees with the differences as s falls, until
round-off; a wrong one stays off by the same amount at every step.

    python benchmarks/bench_gradient.py [--fmu vldm|dc_drive|PATH] [--solver rk4|euler] [--t0 T]
                                        [--span S] [--directions N] [--no-event-gradients]
"""
from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from fmubuilder.build import example_fmu
from fmubuilder.neural import NeuralFMU, TopologyConfig, simulate
from fmubuilder.neural.train import network_parameters

# Per example: (channel, ANN inputs, recorded signals, start values).
SET_UPS = {
    "vldm": ("der(speed)", ["speed"], ["speed", "power", "energy"], {"cycle": 1}),
    "dc_drive": ("der(speed)", ["speed"], ["speed", "current", "temperature"], {}),
}
STEPS = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6)


def set_up(fmu: str, channel: str | None, inputs: list[str] | None, record: list[str] | None, seed: int):
    known = SET_UPS.get(fmu)
    path = example_fmu(fmu) if known else fmu
    channel, inputs, record, start_values = (channel or known[0], inputs or known[1], record or known[2],
                                             known[3]) if known else (channel, inputs, record, {})
    torch.manual_seed(seed)
    model = NeuralFMU(path, TopologyConfig(channels=[channel], inputs=inputs, hidden=[16, 16], kind="residual"),
                      start_values=start_values)
    return model, channel, record


def activate(model, reference, channel: str, inputs: list[str]) -> None:
    """Scaling from the plain run, and a last layer of small random weights: a correction of about
    5 % of the channel's spread (residual topologies start at exactly zero)."""
    samples = np.stack([reference.numpy(name)[:, 0] for name in inputs], axis=1)
    model.topology.initialise_scaling(samples, reference.numpy(channel)[:, :1])
    with torch.no_grad():
        last = model.topology.ann[-1]
        last.weight.normal_(0.0, 0.05)
        last.bias.normal_(0.0, 0.05)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fmu", default="vldm", help="vldm, dc_drive or the path of an FMU (then give --channel ...)")
    parser.add_argument("--channel")
    parser.add_argument("--inputs", nargs="*")
    parser.add_argument("--record", nargs="*")
    parser.add_argument("--solver", choices=["rk4", "euler"], default="rk4")
    parser.add_argument("--step", type=float, default=0.01)
    parser.add_argument("--t0", type=float, default=200.0, help="element start, seconds into the plain run")
    parser.add_argument("--span", type=float, default=20.0)
    parser.add_argument("--directions", type=int, default=3, help="random directions besides the per-tensor ones")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-event-gradients", action="store_true", help="simulate(event_gradients=False)")
    parser.add_argument("--steps", type=float, nargs="*", default=list(STEPS), help="relative steps of the differences")
    parser.add_argument("--no-tensors", action="store_true", help="only -g and the random directions")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model, channel, record = set_up(args.fmu, args.channel, args.inputs, args.record, args.seed)
    inputs = model.config.inputs
    names = list(dict.fromkeys(record + inputs + [channel]))
    with torch.no_grad():   # the plain FMU: the start (captured) and the "data" of the loss
        k0 = int(round(args.t0 / args.step))
        warm = simulate(model, args.t0 + args.span, args.step, record=names, solver=args.solver, capture=[k0])
        start = warm.captured[k0][0]
        plain = simulate(model, args.span, args.step, starts=[start], record=record, solver=args.solver)
    activate(model, warm, channel, inputs)
    target = plain.values.detach()
    scale = target.var(dim=0).clamp_min(1e-12)

    def loss() -> torch.Tensor:
        run = simulate(model, args.span, args.step, starts=[start], record=record, solver=args.solver,
                       event_gradients=not args.no_event_gradients)
        loss.stats = run.stats
        return (((run.values - target) ** 2).mean(dim=0) / scale).mean()

    params = network_parameters(model.topology, [p for p in model.topology.parameters() if p.requires_grad])
    value = loss()
    value.backward()
    g = torch.cat([p.grad.flatten() for p in params])
    theta = torch.cat([p.detach().flatten() for p in params])
    with torch.no_grad():
        value_no_grad = float(loss())
    stats = loss.stats
    print(f"{args.fmu}: {args.solver} h={args.step}, element [{args.t0:g}, {args.t0 + args.span:g}] s, "
          f"event gradients {'off' if args.no_event_gradients else 'on'}; {stats['steps']} steps, "
          f"{stats['time_events']} time events, {stats['state_events']} state events")
    print(f"loss {float(value.detach()):.10g} (with gradient) {value_no_grad:.10g} (without), |g| {float(g.norm()):.4g}, "
          f"|theta| {float(theta.norm()):.4g}")

    def at(shift: torch.Tensor) -> float:
        with torch.no_grad():
            torch.nn.utils.vector_to_parameters(theta + shift, params)
            return float(loss())

    directions = [("-g", -g / g.norm())]
    generator = torch.Generator().manual_seed(args.seed + 1)
    for i in range(args.directions):
        d = torch.randn(theta.shape, generator=generator, dtype=theta.dtype)
        directions.append((f"random {i}", d / d.norm()))
    offset = 0
    for index, p in enumerate([] if args.no_tensors else params):
        d = torch.zeros_like(theta)
        d[offset:offset + p.numel()] = torch.randn(p.numel(), generator=generator, dtype=theta.dtype)
        offset += p.numel()
        directions.append((f"tensor {index} {tuple(p.shape)}", d / d.norm()))
    print("| direction | autograd | " + " | ".join(f"central {s:g}" for s in args.steps) + " |")
    print("|---|---|" + "---|" * len(args.steps))
    for label, d in directions:
        slopes = []
        for relative in args.steps:
            s = relative * float(theta.norm())
            slopes.append((at(s * d) - at(-s * d)) / (2 * s))
        print(f"| {label} | {float(g @ d):.6g} | " + " | ".join(f"{x:.6g}" for x in slopes) + " |", flush=True)
    torch.nn.utils.vector_to_parameters(theta, params)
    model.close()
    if not math.isfinite(float(value)):
        raise SystemExit("error: the loss is not finite")


if __name__ == "__main__":
    main()
