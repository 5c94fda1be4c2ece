"""Klippy extras module (test support): an extruder without hardware, so E moves are accepted and counted.

Klippy runs here in its debug-output mode with no micro-controller, so it has no
``[extruder]`` (that needs a stepper and a heater on an MCU) and refuses every move
with an E word ("Extrude when no extruder present"). Klipper's ``exclude_object``
needs real extrusion moves to follow the extruder before it starts skipping an
object, so an object-cancel test needs E moves. This module, loaded by the config
section ``[layerwatch_test_extruder]``, installs itself as the toolhead's extruder at
connect time: it accepts every E move and adds up the filament it was asked to push
(``printer.objects.query layerwatch_test_extruder`` -> ``extruded``, mm), which is
what the printed objects really received. Nothing else in Klippy is changed.
"""


class LayerwatchTestExtruder:
    def __init__(self, config):
        self.printer = config.get_printer()
        self.extruded = 0.0
        self.printer.register_event_handler("klippy:connect", self._connect)

    def _connect(self):
        self.printer.lookup_object("toolhead").set_extruder(self, 0.0)

    # the toolhead's extruder interface (kinematics/extruder.py)
    def update_move_time(self, flush_time, *args):
        pass

    def check_move(self, move):
        pass

    def move(self, print_time, move):
        self.extruded += move.axes_d[3]

    def find_past_position(self, print_time):
        return 0.0

    def calc_junction(self, prev_move, move):
        return move.max_cruise_v2

    def get_name(self):
        return "extruder"

    def get_heater(self):
        raise self.printer.command_error("the test extruder has no heater")

    def get_trapq(self):
        return None

    def get_status(self, eventtime):
        return {"extruded": round(self.extruded, 4)}


def load_config(config):
    return LayerwatchTestExtruder(config)
