"""The student: observations with realistic noise, a recurrent policy, distilled from a
teacher with a KL loss (``student``, ``config``, ``trainer``)."""
