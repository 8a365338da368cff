"""The two Prophesee RAW headers of issue 25, verbatim: an EVT 3.0 file from a Gen4.1 kit (1280×720)
and an EVT 2.0 file from a Gen3 kit (640×480), whose ``% evt`` line comes last."""

GEN41_EVT3 = (
    "% Date 2020-09-25 07:48:29\n% evt 3.0\n% firmware_version 3.2.3\n% integrator_name Prophesee\n"
    "% plugin_name hal_plugin_gen41_evk3\n% serial_number 00000307\n% system_ID 48\n"
)
GEN3_EVT2 = (
    "% Date 2020-09-14 09:03:25\n% firmware_version 2.0.2\n% integrator_name Prophesee\n"
    "% plugin_name hal_plugin_gen3_fx3\n% serial_number 30384338\n% system_ID 21\n% evt 2.0\n"
)
