"""Recording ROS topics to rosbag2-compatible MCAP files and reading them back, by role:

* :mod:`~cdpr_dynamics.recording.base`: errors, what is read back, type names, the ``mcap``
  writer settings every file here shares;
* :mod:`~cdpr_dynamics.recording.cdr`: CDR bytes of rclpy messages as DDS sends them;
* :mod:`~cdpr_dynamics.recording.writer`: :class:`RecordingWriter` (given messages, written
  under a temporary name) and :class:`ChunkedFile` (the recorder's file, kept readable when the
  disk fills);
* :mod:`~cdpr_dynamics.recording.recorder`: :class:`Recorder`, the recorder node;
* :mod:`~cdpr_dynamics.recording.reader`: :func:`read_messages`, :func:`recording_info`;
* :mod:`~cdpr_dynamics.recording.recovery`: :func:`recover_recording`.

Import from the module of the role (``from cdpr_dynamics.recording.reader import
read_messages``); this package file imports nothing.
"""
