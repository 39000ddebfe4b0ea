"""`extra_node`: an unmodelled thermal mass, in series on a path or hanging off a node."""

from __future__ import annotations

import dataclasses

import numpy as np

from .._spec import Boundary, Link, Node, Parameter
from ._base import AbstractEffect, ParameterLink, fail, param, path_between



class ExtraNode(AbstractEffect):
    kind = "extra_node"

    def lower(self, spec, effect):
        new = effect.name
        a = effect.where[0]
        c = param(effect, "capacitance", 1.0)
        g = param(effect, "conductance", 1.0)
        g_b = param(effect, "conductance_b", 1.0)
        # The mass's own diffusion (°C/√s, Kalman likelihood): fixed at zero unless given,
        # as CTSM-R gives every state of a building model its own.
        q = effect.parameters.get("process_noise", Parameter(0.0, True))
        nodes = spec.nodes + (Node(new, c, process_noise=q, added_by_effect=True),)
        links = list(spec.links)
        bounds = list(spec.boundaries)
        heats = list(spec.heat_inputs)
        pairs = [ParameterLink("capacitance", f"nodes.{new}.capacitance"),
                 ParameterLink("conductance", f"links.{a}-{new}.conductance")]
        if "process_noise" in effect.parameters:
            pairs.append(ParameterLink("process_noise", f"nodes.{new}.process_noise"))
        link_a = Link((a, new), g)
        if len(effect.where) == 1:
            links.append(link_a)
        else:
            b = effect.where[1]
            on_heat = [i for i, h in enumerate(heats) if h.node == a and h.input == b]
            path = path_between(spec, a, b)
            if on_heat:  # the power now enters the mass, which conducts to a
                for i in on_heat:
                    heats[i] = dataclasses.replace(heats[i], node=new)
                links.append(link_a)
            elif path is None:
                fail(spec, effect, f"extra_node [{a}, {b}]: there is no link or boundary "
                     f"between '{a}' and '{b}' to put the mass on; name a linked pair, or use "
                     f"where = [\"{a}\"] for a mass hanging off '{a}'.")
            elif path[0] == "link":
                links.pop(path[1])
                links += [link_a, Link((new, b), g_b)]
                pairs.append(ParameterLink("conductance_b", f"links.{new}-{b}.conductance"))
            else:
                old = bounds.pop(path[1])
                links.append(link_a)
                bounds.append(Boundary(new, b, g_b, old.hold))
                pairs.append(ParameterLink("conductance_b", f"boundaries.{new}-{b}.conductance"))
        return spec.replace(nodes=nodes, links=tuple(links), boundaries=tuple(bounds),
                            heat_inputs=tuple(heats)), pairs

    def places(self, spec, columns):
        out = [tuple(k.between) for k in spec.links]
        out += [(b.node, b.input) for b in spec.boundaries]
        out += [(h.node, h.input) for h in spec.heat_inputs]
        out += [(n,) for n in spec.node_names]
        return out

    def initial_parameters(self, spec, where):
        caps = {n.name: n.capacitance.value for n in spec.nodes}
        c = 0.2 * caps[where[0]]
        if len(where) == 2:
            path = path_between(spec, *where)
            if path is not None:
                g = (spec.links[path[1]].conductance.value if path[0] == "link"
                     else spec.boundaries[path[1]].conductance.value)
                return {"capacitance": c, "conductance": 2 * g, "conductance_b": 2 * g}
        return {"capacitance": c, "conductance": c / 200.0, "conductance_b": c / 200.0}

    def direction_time_constant(self, ctx, j):
        return ctx.trial_time_constants()[j]

    def with_time_constant(self, spec, where, params, tau):
        # local time constant: C over the conductances touching the mass
        out = dict(params)
        if len(where) == 2 and path_between(spec, *where) is not None:
            out["capacitance"] = tau * (out["conductance"] + out["conductance_b"])
        else:  # hanging, or on a heat input's path: the one link to `a`
            out["conductance"] = out["capacitance"] / tau
        return out

    def score_direction(self, ctx, where):
        # A hidden mass is seen through its own time constant, which the first-order
        # score cannot know: one direction per trial time constant, the best one scores.
        a = ctx.node(where[0])
        out = []
        if len(where) == 1:
            for tau in ctx.trial_time_constants():  # heat G (T_m - T_a) per unit C, T_m = lag(T_a)
                Ta = ctx.T[..., a]
                w = np.zeros_like(ctx.T)
                w[..., a] = (ctx.lag(Ta, tau) - Ta) / tau
                out.append(w)
            return "heat", out
        b = where[1]
        if ctx.is_heat_column(where[0], b):  # the power reaches a through a lag
            q = ctx.column(b)
            for tau in ctx.trial_time_constants():
                w = np.zeros_like(ctx.T)
                w[..., a] = ctx.lag(q, tau) - q
                out.append(w)
            return "heat", out
        Tb = ctx.temperature(b)
        for tau in ctx.trial_time_constants():  # a mass at the path's midpoint, lagging it
            mid = 0.5 * (ctx.T[..., a] + Tb)
            flow = (ctx.lag(mid, tau) - mid) / tau  # W per J/K of the mass, split half/half
            w = np.zeros_like(ctx.T)
            w[..., a] = 0.5 * flow
            if ctx.is_node(b):
                w[..., ctx.node(b)] += 0.5 * flow
            out.append(w)
        return "heat", out
