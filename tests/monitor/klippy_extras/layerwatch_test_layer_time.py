"""Klippy extras module (test support): make a layer take real time.

Klippy runs here in its debug-output mode (``-o /dev/null -d <dict>``: no
micro-controller, commands go to /dev/null). In that mode the toolhead never
waits for the (non-existent) MCU clock, so ``G4`` dwells and moves finish
instantly and a whole print would be over before a pause could reach it.
This module adds one G-code command that waits in real time on Klippy's
reactor, the way a real layer takes time to print::

    LAYERWATCH_TEST_LAYER_TIME SECONDS=0.3

While it waits, Klippy keeps serving its API socket (Moonraker's requests,
``PAUSE`` queued behind the running command like on a real printer).

It is copied into the test Klippy's ``klippy/extras`` folder (Klipper's own
way of adding modules) by the test fixture and loaded by the config section
``[layerwatch_test_layer_time]``. Nothing else in Klippy is changed.
"""


class LayerwatchTestLayerTime:
    def __init__(self, config):
        self.printer = config.get_printer()
        gcode = self.printer.lookup_object("gcode")
        gcode.register_command("LAYERWATCH_TEST_LAYER_TIME", self.cmd_LAYER_TIME,
                               desc="Wait SECONDS of real time (test support)")

    def cmd_LAYER_TIME(self, gcmd):
        seconds = gcmd.get_float("SECONDS", 0.3, minval=0.0, maxval=30.0)
        reactor = self.printer.get_reactor()
        reactor.pause(reactor.monotonic() + seconds)


def load_config(config):
    return LayerwatchTestLayerTime(config)
