// arena_robot: reference firmware for the Zumo 32U4 robots of the arena lab.
//
// Speaks the arena robot wire protocol (docs/robot-protocol.md) on Serial1 at 57600 baud
// (the Bluetooth SPP module, e.g. an HC-05/RN-42 on the Zumo's expansion header), and on
// the USB Serial too, so the same robot can be driven over /dev/rfcommN or /dev/ttyACM0.
//
//  * SET_MOTORS -> Zumo32U4Motors::setSpeeds(left, right), -400..400.
//  * Watchdog: no SET_MOTORS for WATCHDOG_MS (300 ms) -> motors 0, FLAG_WATCHDOG set.
//  * TELEMETRY every 1000/TELEMETRY_HZ ms: cumulative 32-bit encoder counts (the library's
//    16-bit counters are read-and-reset and accumulated here), IMU raw (accel +-2 g,
//    gyro +-2000 dps, mag +-4 gauss), battery mV, applied motor power, flags.
//  * PING -> PONG with the same token; HELLO -> HELLO_REPLY; SET_LED; STOP.
//
// Framing and CRC live in arena_proto.c/.h, which the host tests compile with gcc and
// compare byte for byte with arena/robot_protocol.py.
//
// Build: Arduino IDE or arduino-cli with the Pololu A-Star 32U4 board package and the
// Zumo32U4 library:  arduino-cli compile -b pololu-a-star:avr:a-star32U4 arena_robot

#include <Wire.h>
#include <Zumo32U4.h>
#include "arena_proto.h"

#ifndef ROBOT_NAME
#define ROBOT_NAME "zumo"
#endif
#define FIRMWARE_VERSION 1
#define BAUD 57600
#define TELEMETRY_HZ 50      // 45-byte frames: 50 Hz uses ~40 % of 57600 baud
#define WATCHDOG_MS 300
#define COUNTS_PER_REV 1807  // 150:1 motors, 12 CPR encoder
#define LOW_BATTERY_MV 4400  // 4 x AA NiMH nearly empty

#define FLAG_WATCHDOG 0x01
#define FLAG_LOW_BATTERY 0x02

Zumo32U4Motors motors;
Zumo32U4Encoders encoders;
Zumo32U4IMU imu;

static ap_decoder decSerial1, decUsb;
static uint16_t txSeq = 0;
static int32_t encLeft = 0, encRight = 0;
static int16_t powerLeft = 0, powerRight = 0;
static uint8_t flags = 0;
static uint32_t lastMotorMs = 0, lastTelemetryMs = 0;
static bool imuOk = false;
static Stream *replyPort = &Serial1;

static void sendFrame(Stream &port, uint8_t type, const uint8_t *body, size_t len) {
  uint8_t out[AP_MAX_FRAME];
  size_t n = ap_encode_frame(type, txSeq++, micros(), body, len, out);
  port.write(out, n);
}

static void broadcast(uint8_t type, const uint8_t *body, size_t len) {
  sendFrame(Serial1, type, body, len);
  if (Serial) sendFrame(Serial, type, body, len);  // USB only when a host opened it
}

static void setPower(int16_t left, int16_t right) {
  powerLeft = constrain(left, -400, 400);
  powerRight = constrain(right, -400, 400);
  motors.setSpeeds(powerLeft, powerRight);
}

static void sendError(uint8_t code, uint8_t refType) {
  uint8_t body[26] = {code, refType};
  sendFrame(*replyPort, AP_ERROR, body, sizeof body);
}

static void handlePacket(const uint8_t *p, size_t n) {
  const uint8_t *body = p + AP_HEADER_SIZE;
  size_t len = n - AP_HEADER_SIZE - 2;
  switch (ap_type(p)) {
    case AP_HELLO: {
      uint8_t r[24] = {0};
      ap_put_u16(r, FIRMWARE_VERSION);
      ap_put_u16(r + 2, TELEMETRY_HZ);
      ap_put_u16(r + 4, COUNTS_PER_REV);
      ap_put_u16(r + 6, WATCHDOG_MS);
      strncpy((char *)r + 8, ROBOT_NAME, 16);
      sendFrame(*replyPort, AP_HELLO_REPLY, r, sizeof r);
      break;
    }
    case AP_SET_MOTORS:
      if (len != 4) { sendError(AP_ERR_BAD_LENGTH, AP_SET_MOTORS); break; }
      setPower(ap_get_i16(body), ap_get_i16(body + 2));
      lastMotorMs = millis();
      flags &= ~FLAG_WATCHDOG;
      break;
    case AP_SET_LED:
      if (len != 3) { sendError(AP_ERR_BAD_LENGTH, AP_SET_LED); break; }
      ledRed(body[0] > 127);   // the Zumo's own LEDs; an RGB ring would take all three bytes
      ledGreen(body[1] > 127);
      ledYellow(body[2] > 127);
      break;
    case AP_STOP:
      setPower(0, 0);
      break;
    case AP_PING:
      if (len != 4) { sendError(AP_ERR_BAD_LENGTH, AP_PING); break; }
      sendFrame(*replyPort, AP_PONG, body, 4);
      break;
    default:
      sendError(AP_ERR_UNKNOWN_TYPE, ap_type(p));
  }
}

static void pump(Stream &port, ap_decoder &dec) {
  while (port.available()) {
    if (ap_decoder_feed(&dec, (uint8_t)port.read()) == AP_FRAME) {
      replyPort = &port;
      handlePacket(dec.packet, dec.len);
    }
  }
}

static void sendTelemetry() {
  encLeft += encoders.getCountsAndResetLeft();
  encRight += encoders.getCountsAndResetRight();
  if (imuOk) imu.read();
  uint16_t mv = readBatteryMillivolts();
  if (mv < LOW_BATTERY_MV && !usbPowerPresent()) flags |= FLAG_LOW_BATTERY; else flags &= ~FLAG_LOW_BATTERY;
  uint8_t b[33];
  ap_put_u32(b, (uint32_t)encLeft);
  ap_put_u32(b + 4, (uint32_t)encRight);
  const int16_t v[9] = {imu.a.x, imu.a.y, imu.a.z, imu.g.x, imu.g.y, imu.g.z, imu.m.x, imu.m.y, imu.m.z};
  for (uint8_t i = 0; i < 9; i++) ap_put_u16(b + 8 + 2 * i, (uint16_t)v[i]);
  ap_put_u16(b + 26, mv);
  ap_put_u16(b + 28, (uint16_t)powerLeft);
  ap_put_u16(b + 30, (uint16_t)powerRight);
  b[32] = flags;
  broadcast(AP_TELEMETRY, b, sizeof b);
}

void setup() {
  Serial1.begin(BAUD);
  Serial.begin(BAUD);
  Wire.begin();
  imuOk = imu.init();
  if (imuOk) {
    imu.enableDefault();
    imu.configureForTurnSensing();  // gyro +-2000 dps
  }
  ap_decoder_init(&decSerial1);
  ap_decoder_init(&decUsb);
  setPower(0, 0);
  encoders.getCountsAndResetLeft();
  encoders.getCountsAndResetRight();
  Serial1.write((uint8_t)0);  // delimiter: the host's decoder resynchronises on it
}

void loop() {
  pump(Serial1, decSerial1);
  pump(Serial, decUsb);
  uint32_t now = millis();
  if ((powerLeft || powerRight) && now - lastMotorMs > WATCHDOG_MS) {
    setPower(0, 0);
    flags |= FLAG_WATCHDOG;
  }
  if (now - lastTelemetryMs >= 1000 / TELEMETRY_HZ) {
    lastTelemetryMs = now;
    sendTelemetry();
  }
}
