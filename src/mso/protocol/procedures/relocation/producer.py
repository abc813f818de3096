"""A producer of a moving vertex: switches its edge to the new host and sends a marker the old
way."""

from __future__ import annotations

from mso.protocol import messages as m
from mso.protocol.effects import Send
from mso.protocol.procedures.relocation._role import Role
from mso.protocol.state import AppState


class Producer(Role):
    """At the node of a producer of the vertex that moves."""

    def on_switch(self, src: str, msg: m.Switch) -> None:
        """At the producer's node: new events go to the new instance; a marker goes the old way."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None or not 0 <= msg.edge < len(dep.app.edges):
            self.ctx.refusal("switch_unknown_edge")
            return
        edge = dep.app.edges[msg.edge]
        if dep.switched.get(msg.edge) == msg.rid:  # sent again: this edge switched already
            self._mark_again(dep, msg)
            return
        if self.unwarranted(dep, src, edge.dst, msg.rid, msg.order):
            return
        old = dep.placed[edge.dst]
        if old == msg.to and msg.source:  # a merge vertex whose other input, produced here
            old = msg.source  # too, switched first: its marker goes the old way as well
        why = self._switch_refused(dep, edge.src, edge.dst, msg.to, old)
        if not why and msg.to == self.ctx.id and not self.prepared_for(msg.app, edge.dst, msg.rid):
            # a switch to this node, which holds no instance prepared for the move: the old
            # host would hand the vertex over to nothing and free it. A restarted target is
            # sent its last process's Switch (the control stream sends it again when a route
            # appears, before its sender hears of the restart; fault seed 314611: the new
            # process marked the edge, the vertex's host handed it over and it ran nowhere)
            why = "switch_to_no_prepared_instance"
        if why:
            self.ctx.refusal(why)
            return
        key = (msg.app, msg.edge)
        batch = self.dp.outbox.pop(key, None)
        if batch is not None:  # what is already queued leaves before the marker
            data = m.Data(msg.app, msg.edge, dep.epoch, *batch)
            data.gens = self.dp.stamp_gens(dep, msg.edge)
            self.ctx.emit(Send(old, data))
        seq = self.dp.out(dep, msg.edge).next_seq
        dep.placed[edge.dst] = msg.to
        dep.switched[msg.edge] = msg.rid
        dep.vanished.discard(edge.dst)  # the move's coordinator sees to it from now on (it
        # restores it at the target if the old host went; the target does if the coordinator
        # went too: NewHost.orphaned); a recovery here would make a twin
        marker = m.Marker(msg.app, msg.edge, seq, msg.rid, msg.to)
        if old == self.ctx.id:
            self.dp.enqueue(dep, edge.dst, marker)
        else:
            dep.marked_to[msg.edge] = (old, marker)
            self.ctx.emit(Send(old, marker))

    def _mark_again(self, dep: AppState, msg: m.Switch) -> None:
        """The move's coordinator sent its Switch again (no handover yet): this edge switched
        already, but its marker may be what was lost on the way (a marker goes unsequenced,
        in order with the events, and the move waited for it the switch's 60 s, the target
        holding the app: control loss seed 134), so it goes again, the same. A second one is
        nothing at the old host: it comes behind the first, and after the handover there is
        no instance to meet it. Only while this node's view still places the vertex where
        the move took it (a later move's switch here: the old host may host it again)."""
        sent = dep.marked_to.get(msg.edge)
        vid = dep.app.edges[msg.edge].dst
        if sent is None or sent[1].rid != msg.rid or dep.placed.get(vid) != msg.to:
            self.ctx.dropped()
            return
        self.ctx.emit(Send(*sent))

    def prepared_for(self, app: str, vertex: str, rid: int) -> bool:
        """An instance of ``vertex`` awaits here the handover of move ``rid`` (the new host's
        role answers: :meth:`.new_host.NewHost.prepared_for`)."""
        raise NotImplementedError

    def _switch_refused(
        self, dep: AppState, producer: str, consumer: str, to: str, old: str
    ) -> str:
        """Why a Switch cannot be part of a relocation ('' if it can): a relocation never
        moves a pinned vertex, nor to where it runs already (its instance would be handed
        over to nobody; ``old`` is where it runs, the move's source once another input of
        the vertex switched here). With operator keys, the producer must run here and ``to``
        be a node this one can reach."""
        if to == old:
            return "switch_to_where_it_runs"
        if dep.app.vertices[consumer].pinned is not None:
            return "switch_of_a_pinned_vertex"
        if self.ctx.authority.signed:
            if producer not in dep.instances:
                return "switch_not_the_producer"
            if to != self.ctx.id and to not in self.ctx.routes:
                return "switch_to_an_unknown_node"
        return ""
