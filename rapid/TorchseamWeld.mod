MODULE TorchseamWeld
    !==========================================================================
    ! TorchseamWeld: runs a weld segment by segment, the torchseam laser sensor
    ! guiding the torch over ABB Externally Guided Motion (EGM, option 689-1;
    ! UdpUc device, position guidance, pose mode).
    !
    ! For each segment: RAPID moves the torch to the segment's start (phase
    ! TO_START), activates EGM with the data channel and starts the guided
    ! motion without waiting (phase GUIDED), then watches the sensor's data:
    ! the arc output follows the sensor's arc request while the sensor's
    ! heartbeat advances; the segment ends when the sensor says DONE or ABORT,
    ! when the heartbeat stops, when EGM stops, or on EGM's communication
    ! timeout. Then: arc off, EGMStop, phase TAKEN_BACK, next segment. At the
    ! end: phase ENDED.
    !
    ! The data channel (EgmSensor.RAPIDtoRobot, EgmRobot.RAPIDfromRobot) and
    ! what its values mean: torchseam/robot/egm/rapid_data.py. The CONSTs below
    ! carry its names and values; its dnum indices count from 0, RAPID's
    ! arrays from 1, hence every index is written {NAME + 1}.
    !
    ! What was verified:
    ! - every index and enum value below equals rapid_data.py's, and the two
    !   dnum arrays are indexed only with those names
    !   (tests/test_rapid_module.py, which also balances the blocks);
    ! - `torchseam robot rapid` prints this file as shipped.
    ! What was NOT verified:
    ! - this module has not run on a controller, nor in RobotStudio: it has
    !   not even been loaded, so syntax and semantics are unchecked by ABB's
    !   compiler. Test it in RobotStudio (virtual controller) first.
    ! - the data channel's RAPID side was not found in ABB's RAPID reference
    !   (not reachable here). It is taken from public EGM examples:
    !   EGMActPose ... \DataToSensor:=<dnum array> \DataFromSensor:=<dnum
    !   array> (PERS dnum arrays of 40 elements; the ABBRobotEGM library's
    !   example for RobotWare 7) and \DOToSensor:=<DO> \DIFromSensor:=<DI>
    !   (same library; a ROS EGM driver's README: the DI must be a signal
    !   defined in the I/O configuration). The order of these optional
    !   arguments among the others, the array length EGM accepts, and whether
    !   RobotWare 6 on an IRC5 has them at all are unverified: check the
    !   controller's RAPID reference (EGMActPose) and its egm.proto.
    ! - \CommTimeout is an argument of EGMSetupUC in every example found
    !   (seconds, as they use it); ERR_UDPUC_COMM is the timeout's error. One
    !   secondary source quotes ABB's EGM manual as saying that with
    !   \NoWaitCond the timeout is raised as a fatal error, which no ERROR
    !   handler catches: if so the program stops there and the welder must
    !   drop the arc on its own interlock (program stopped / motion stopped).
    !   That is why the loop has its own, shorter timeout: the sensor's
    !   heartbeat (HB_GIVEUP_S < COMM_TIMEOUT_S) ends the segment first.
    ! - that streaming (\StreamStart) carries RAPIDfromRobot between segments
    !   (after EGMStop) and until EGMReset; the sensor hears RAPID's data from
    !   the first EGMActPose on (segment 1's TO_START is not sent).
    !
    ! The integrator fills in (placeholders, marked PLACEHOLDER):
    ! - the I/O signals, defined in the I/O configuration (not here):
    !     doArcOn     DO to the welder: arc on
    !     diArcEst    DI from the welder: arc established
    !     diTsArcReq  DI that EGM sets from the sensor's arc request
    !                 (RAPIDtoRobot.digVal; \DIFromSensor)
    !     doTsArcEst  DO whose value EGM sends as arc on
    !                 (RAPIDfromRobot.digVal; \DOToSensor)
    ! - UC_DEVICE, EGM_CONFIG (Communication > Transmission Protocol; Motion >
    !   External Motion Interface Data), tTorch (the TCP of cell.yaml's tool),
    !   pSegStart (one start pose per segment, in path order, in the base frame:
    !   the pre-flight's start poses, `torchseam plan --out DIR`), then sets
    !   segmentsTaught := TRUE. Everything is commanded in wobj0 (the base
    !   frame), as the sensor's targets are torch-tip poses in the base frame.
    !==========================================================================

    !--- the channel's layout: torchseam/robot/egm/rapid_data.py ---------------
    ! dnum indices of the sensor's data (EgmSensor.RAPIDtoRobot)
    CONST num SENSOR_SEGMENT := 0;
    CONST num SENSOR_STATE := 1;
    CONST num SENSOR_HEARTBEAT := 2;
    ! dnum indices of RAPID's data (EgmRobot.RAPIDfromRobot)
    CONST num RAPID_SEGMENT := 0;
    CONST num RAPID_PHASE := 1;
    CONST num RAPID_N_SEGMENTS := 2;
    ! the heartbeat counts modulo this
    CONST num HEARTBEAT_MODULO := 1048576;
    ! the sensor's states
    CONST num STATE_WAIT := 0;
    CONST num STATE_TRACKING := 1;
    CONST num STATE_DONE := 2;
    CONST num STATE_ABORT := 3;
    ! RAPID's phases
    CONST num PHASE_IDLE := 0;
    CONST num PHASE_TO_START := 1;
    CONST num PHASE_GUIDED := 2;
    CONST num PHASE_TAKEN_BACK := 3;
    CONST num PHASE_ENDED := 4;

    !--- settings -------------------------------------------------------------
    ! PLACEHOLDER: the UdpUc device (Transmission Protocol) and EGM config names
    CONST string UC_DEVICE := "TORCHSEAM";
    CONST string EGM_CONFIG := "default";
    ! EGMSetupUC \CommTimeout, s: no sensor message for this long is an error
    CONST num COMM_TIMEOUT_S := 1;
    ! the sensor's heartbeat unchanged this long: arc off ...
    CONST num HB_STALE_S := 0.1;
    ! ... this long: the segment is given up (shorter than COMM_TIMEOUT_S)
    CONST num HB_GIVEUP_S := 0.5;
    ! a segment still guided after this long is given up, s
    CONST num SEG_MAX_S := 600;
    ! the watch loop's period, s
    CONST num LOOP_S := 0.012;
    ! approach and retreat distance along the base frame's z, mm
    CONST num APPROACH_MM := 50;
    ! EGM: convergence ranges (mm, deg), the time they must hold before EGM
    ! ends the motion by itself (s: longer than any segment, so a sensor
    ! holding the torch still does not end it), ramp-in (s), sample rate (ms),
    ! low-pass filter (Hz), largest position (mm) and speed (deg/s) deviations
    CONST egm_minmax CONV_LIN := [-0.5,0.5];
    CONST egm_minmax CONV_ROT := [-0.5,0.5];
    CONST num COND_TIME_S := 600;
    CONST num RAMP_IN_S := 0.05;
    CONST num SAMPLE_MS := 4;
    CONST num LP_FILTER_HZ := 20;
    CONST num MAX_POS_DEV := 30;
    CONST num MAX_SPEED_DEV := 20;
    ! the sensor sends the torch pose (TCP) in the robot base frame
    CONST pose CORR_FRAME := [[0,0,0],[1,0,0,0]];
    CONST pose SENS_FRAME := [[0,0,0],[1,0,0,0]];
    ! why a segment ended
    CONST num END_DONE := 1;
    CONST num END_ABORT := 2;
    CONST num END_HEARTBEAT := 3;
    CONST num END_EGM_STOPPED := 4;
    CONST num END_OVERTIME := 5;
    CONST num END_COMM_TIMEOUT := 6;

    !--- the cell (PLACEHOLDER values: teach them) ------------------------------
    PERS bool segmentsTaught := FALSE;
    PERS tooldata tTorch := [TRUE,[[0,0,350],[1,0,0,0]],[3,[0,0,120],[1,0,0,0],0,0,0]];
    PERS robtarget pSegStart{2} := [
        [[800,-100,400],[0,0,1,0],[0,0,0,0],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]],
        [[800,100,400],[0,0,1,0],[0,0,0,0],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]]];
    PERS speeddata vAir := [200,100,5000,1000];
    PERS speeddata vApproach := [50,50,5000,1000];

    !--- the data channel, linked by EGMActPose ----------------------------------
    PERS dnum dnFromSensor{40};
    PERS dnum dnToSensor{40};

    VAR egmident egmId;
    VAR num nSeg := 0;
    VAR clock clkHb;
    VAR clock clkSeg;

    PROC main()
        IF NOT segmentsTaught THEN
            ErrWrite "TorchseamWeld: not taught",
                "Teach tTorch and pSegStart, then set segmentsTaught := TRUE.";
            RETURN;
        ENDIF
        nSeg := Dim(pSegStart, 1);
        SetDO doArcOn, 0;
        SetDO doTsArcEst, 0;
        SetPhase 0, PHASE_IDLE;
        ! a DONE left in the PERS array by an earlier run must not end a segment
        ClearSensorData;
        EGMReset egmId;
        EGMGetId egmId;
        EGMSetupUC ROB_1, egmId, EGM_CONFIG, UC_DEVICE \Pose \CommTimeout:=COMM_TIMEOUT_S;
        FOR i FROM 1 TO nSeg DO
            RunSegment i;
        ENDFOR
        SetDO doArcOn, 0;
        SetPhase 0, PHASE_ENDED;
        ! let the stream carry ENDED to the sensor before EGM is released
        WaitTime 1;
        EGMReset egmId;
    ERROR
        SetDO doArcOn, 0;
        RAISE;
    ENDPROC

    ! One segment: to its start, guided by the sensor, taken back.
    PROC RunSegment(num seg)
        VAR num state;
        VAR num hb;
        VAR num lastHb;
        VAR bool mine;
        VAR bool fresh;
        VAR num why := 0;

        ! 1. to the segment's start, RAPID's own motion, stopping in a fine point
        SetDO doArcOn, 0;
        SetPhase seg, PHASE_TO_START;
        MoveJ Offs(pSegStart{seg}, 0, 0, APPROACH_MM), vAir, z10, tTorch \WObj:=wobj0;
        MoveL pSegStart{seg}, vApproach, fine, tTorch \WObj:=wobj0;

        ! 2. EGM with the data channel; the guided motion starts, RAPID goes on
        EGMActPose egmId \StreamStart \Tool:=tTorch \WObj:=wobj0
            \DOToSensor:=doTsArcEst \DIFromSensor:=diTsArcReq
            \DataToSensor:=dnToSensor \DataFromSensor:=dnFromSensor,
            CORR_FRAME, EGM_FRAME_BASE, SENS_FRAME, EGM_FRAME_BASE
            \X:=CONV_LIN \Y:=CONV_LIN \Z:=CONV_LIN
            \Rx:=CONV_ROT \Ry:=CONV_ROT \Rz:=CONV_ROT
            \LpFilter:=LP_FILTER_HZ \SampleRate:=SAMPLE_MS
            \MaxPosDeviation:=MAX_POS_DEV \MaxSpeedDeviation:=MAX_SPEED_DEV;
        SetPhase seg, PHASE_GUIDED;
        ! a heartbeat left from the previous segment is not fresh
        lastHb := SensorVal(SENSOR_HEARTBEAT);
        RestartClock clkHb;
        RestartClock clkSeg;
        EGMRunPose egmId, EGM_STOP_HOLD \NoWaitCond \X \Y \Z \Rx \Ry \Rz
            \CondTime:=COND_TIME_S \RampInTime:=RAMP_IN_S;

        ! 3. watch the sensor until the segment ends
        WHILE why = 0 DO
            ! the welder's arc-established signal, to the sensor
            SetDO doTsArcEst, DInput(diArcEst);
            hb := SensorVal(SENSOR_HEARTBEAT);
            IF hb <> lastHb THEN
                lastHb := hb;
                RestartClock clkHb;
            ENDIF
            fresh := ClkRead(clkHb) < HB_STALE_S;
            mine := SensorVal(SENSOR_SEGMENT) = seg;
            state := SensorVal(SENSOR_STATE);
            ! the arc burns only on a live, tracking sensor's request for this segment
            IF fresh AND mine AND state = STATE_TRACKING AND DInput(diTsArcReq) = 1 THEN
                SetDO doArcOn, 1;
            ELSE
                SetDO doArcOn, 0;
            ENDIF
            IF mine AND state = STATE_DONE THEN
                why := END_DONE;
            ELSEIF mine AND state = STATE_ABORT THEN
                why := END_ABORT;
            ELSEIF ClkRead(clkHb) > HB_GIVEUP_S THEN
                why := END_HEARTBEAT;
            ELSEIF EGMGetState(egmId) <> EGM_STATE_RUNNING THEN
                why := END_EGM_STOPPED;
            ELSEIF ClkRead(clkSeg) > SEG_MAX_S THEN
                why := END_OVERTIME;
            ELSE
                WaitTime LOOP_S;
            ENDIF
        ENDWHILE

        ! 4. RAPID takes back: arc off first, then the motion
        SetDO doArcOn, 0;
        EGMStop egmId, EGM_STOP_HOLD;
        SetPhase seg, PHASE_TAKEN_BACK;
        ReportEnd seg, why;
        Retreat;
    ERROR
        IF ERRNO = ERR_UDPUC_COMM THEN
            ! EGM's communication timeout: no message from the sensor
            SetDO doArcOn, 0;
            EGMStop egmId, EGM_STOP_HOLD;
            SetPhase seg, PHASE_TAKEN_BACK;
            ReportEnd seg, END_COMM_TIMEOUT;
            Retreat;
            RETURN;
        ENDIF
        SetDO doArcOn, 0;
        RAISE;
    ENDPROC

    ! RAPID's data for the sensor: segment, phase, number of segments.
    PROC SetPhase(num seg, num phase)
        dnToSensor{RAPID_SEGMENT + 1} := NumToDnum(seg);
        dnToSensor{RAPID_PHASE + 1} := NumToDnum(phase);
        dnToSensor{RAPID_N_SEGMENTS + 1} := NumToDnum(nSeg);
    ENDPROC

    PROC ClearSensorData()
        FOR k FROM 1 TO Dim(dnFromSensor, 1) DO
            dnFromSensor{k} := NumToDnum(0);
        ENDFOR
    ENDPROC

    ! One of the sensor's values, by its index in rapid_data.py.
    FUNC num SensorVal(num idx)
        RETURN DnumToNum(dnFromSensor{idx + 1});
    ENDFUNC

    PROC RestartClock(INOUT clock clk)
        ClkStop clk;
        ClkReset clk;
        ClkStart clk;
    ENDPROC

    ! Away from the part along the base frame's z (check it suits the cell).
    PROC Retreat()
        MoveL Offs(CRobT(\Tool:=tTorch \WObj:=wobj0), 0, 0, APPROACH_MM), vApproach, fine,
            tTorch \WObj:=wobj0;
    ENDPROC

    PROC ReportEnd(num seg, num why)
        VAR string text;
        TEST why
        CASE END_DONE:
            text := "done";
        CASE END_ABORT:
            text := "the sensor aborted";
        CASE END_HEARTBEAT:
            text := "the sensor's heartbeat stopped";
        CASE END_EGM_STOPPED:
            text := "EGM stopped";
        CASE END_OVERTIME:
            text := "overtime";
        CASE END_COMM_TIMEOUT:
            text := "EGM communication timeout";
        DEFAULT:
            text := "unknown";
        ENDTEST
        IF why = END_DONE THEN
            TPWrite "TorchseamWeld: segment " + NumToStr(seg, 0) + ": " + text;
        ELSE
            ErrWrite \W, "TorchseamWeld: segment " + NumToStr(seg, 0),
                "Taken back: " + text + ". Arc off, EGM stopped.";
        ENDIF
    ENDPROC
ENDMODULE
