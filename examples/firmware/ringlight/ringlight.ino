// pstoolkit ring-light controller: firmware for spec/ringlight-protocol.md, version 1.
//
// Hardware: an Arduino (Uno, Nano, Leonardo, Due …) driving a ring of WS2812 ("NeoPixel") RGB LEDs
// on LED_PIN, with two trigger outputs: PERIOD_PIN pulses once per turn (wire it to the frame camera
// and to the event camera's trigger input), EXPOSURE_PIN once per exposure window (frame camera).
// Library: Adafruit NeoPixel (Library Manager). Set LED_COUNT to the ring.
//
// The Python simulator plugins/pstoolkit_ringlight/device.py behaves exactly like this sketch; keep
// the two in step.

#include <Adafruit_NeoPixel.h>

#define FIRMWARE "pstoolkit-ringlight"
#define VERSION "1.0.0"
#define PROTOCOL 1
#define LED_PIN 6
#define LED_COUNT 60
#define PERIOD_PIN 2
#define EXPOSURE_PIN 3
#define PULSE_US 10
#define MAX_LINE 64

enum State { IDLE, SWEEP, SINGLE };

Adafruit_NeoPixel ring(LED_COUNT, LED_PIN, NEO_GRB + NEO_KHZ800);

uint8_t gains[LED_COUNT][3];
char line[MAX_LINE + 2];
uint8_t lineLength = 0;
bool overflow = false;

State state = IDLE;
bool configured = false;
bool watchdogFault = false;
long periodUs = 33333;
int sense = 1;
bool smooth = true;
int triggerMode = 1;
int exposures = 3;
unsigned long turns = 0;         // 0: until STOP
unsigned long startUs = 0;
unsigned long watchdogMs = 1000;
unsigned long lastRxMs = 0;
unsigned long lastPeriodPulse = 0xFFFFFFFF;
unsigned long lastExposurePulse = 0xFFFFFFFF;
unsigned long pulseOffUs = 0;

char lastId[3] = "";
char lastReply[MAX_LINE + 2] = "";

// CRC-8/SMBUS: polynomial 0x07, initial 0, no reflection, no final xor.
uint8_t crc8(const char *data, uint8_t length) {
  uint8_t crc = 0;
  for (uint8_t i = 0; i < length; i++) {
    crc ^= (uint8_t)data[i];
    for (uint8_t bit = 0; bit < 8; bit++) crc = (crc & 0x80) ? (uint8_t)((crc << 1) ^ 0x07) : (uint8_t)(crc << 1);
  }
  return crc;
}

// Writes "!<body>*<crc>\n" into out (which becomes the remembered reply) and sends it.
void reply(const char *body, char *out) {
  snprintf(out, MAX_LINE + 2, "!%s*%02X\n", body, crc8(body, strlen(body)));
  Serial.print(out);
}

void allOff() {
  ring.clear();
  ring.show();
  digitalWrite(PERIOD_PIN, LOW);
  digitalWrite(EXPOSURE_PIN, LOW);
}

void setLed(int led, int r, int g, int b) {
  ring.setPixelColor(led, ring.Color((r * gains[led][0]) / 255, (g * gains[led][1]) / 255, (b * gains[led][2]) / 255));
}

// The sweep at the current time: blend of two neighbouring LEDs (smooth) or one LED per slot,
// plus the trigger pulses. Called from loop() as often as possible.
void runSweep() {
  unsigned long elapsed = micros() - startUs;
  unsigned long turn = elapsed / (unsigned long)periodUs;
  if (turns > 0 && turn >= turns) {
    state = IDLE;
    allOff();
    return;
  }
  unsigned long inTurn = elapsed % (unsigned long)periodUs;
  float position = (float)inTurn * LED_COUNT / periodUs;  // 0 … N
  int slot = (int)position;
  float frac = position - slot;
  int first = sense > 0 ? slot : (LED_COUNT - slot) % LED_COUNT;
  int second = sense > 0 ? (first + 1) % LED_COUNT : (first + LED_COUNT - 1) % LED_COUNT;
  ring.clear();
  int level = smooth ? (int)(255 * (1.0 - frac)) : 255;
  setLed(first, level, level, level);
  if (smooth) setLed(second, 255 - level, 255 - level, 255 - level);
  ring.show();
  if (triggerMode == 1 && turn != lastPeriodPulse) {
    lastPeriodPulse = turn;
    digitalWrite(PERIOD_PIN, HIGH);
    pulseOffUs = micros() + PULSE_US;
  }
  if (triggerMode == 2) {
    unsigned long window = turn * exposures + inTurn * exposures / periodUs;
    if (window != lastExposurePulse) {
      lastExposurePulse = window;
      digitalWrite(EXPOSURE_PIN, HIGH);
      if (window % exposures == 0) digitalWrite(PERIOD_PIN, HIGH);
      pulseOffUs = micros() + PULSE_US;
    }
  }
  if ((long)(micros() - pulseOffUs) >= 0) {
    digitalWrite(PERIOD_PIN, LOW);
    digitalWrite(EXPOSURE_PIN, LOW);
  }
}

// Parses up to maxArgs signed integers after the op; returns their count, or -1 on a bad word.
int parseArgs(char *rest, long *args, int maxArgs) {
  int count = 0;
  char *word = strtok(rest, " ");
  while (word != NULL) {
    if (count == maxArgs) return -1;
    char *end;
    args[count++] = strtol(word, &end, 10);
    if (*end != '\0') return -1;
    word = strtok(NULL, " ");
  }
  return count;
}

// Executes one command; writes the reply body after the id into body. Returns 0 or an error code.
int execute(const char *op, char *rest, char *body, size_t size) {
  long a[5];
  int n = parseArgs(rest, a, 5);
  if (n < 0) return 2;
  body[0] = '\0';
  if (!strcmp(op, "ID")) {
    if (n != 0) return 2;
    snprintf(body, size, " %s %s %d %d", FIRMWARE, VERSION, LED_COUNT, PROTOCOL);
  } else if (!strcmp(op, "PING")) {
    if (n != 0) return 2;
  } else if (!strcmp(op, "STAT")) {
    if (n != 0) return 2;
    const char *names[] = {"IDLE", "SWEEP", "LED"};
    unsigned long done = state == SWEEP ? (micros() - startUs) / (unsigned long)periodUs : 0;
    snprintf(body, size, " %s %lu %lu %s", names[state], done, watchdogMs, watchdogFault ? "WDOG" : "NONE");
  } else if (!strcmp(op, "OFF") || !strcmp(op, "STOP")) {
    if (n != 0) return 2;
    state = IDLE;
    allOff();
  } else if (!strcmp(op, "WDG")) {
    if (n != 1) return 2;
    if (a[0] < 100 || a[0] > 60000) return 4;
    watchdogMs = a[0];
  } else if (!strcmp(op, "CFG")) {
    if (n != 5) return 2;
    if (state == SWEEP) return 5;
    if (a[0] < 1000 || a[0] > 10000000L || a[0] < 2L * LED_COUNT || (a[1] != 1 && a[1] != -1) || a[2] < 0 || a[2] > 1 ||
        a[3] < 0 || a[3] > 2 || a[4] < 1 || a[4] > 100)
      return 4;
    periodUs = a[0]; sense = a[1]; smooth = a[2]; triggerMode = a[3]; exposures = a[4];
    configured = true;
  } else if (!strcmp(op, "CAL")) {
    if (n != 4) return 2;
    if (a[0] < 0 || a[0] >= LED_COUNT || a[1] < 0 || a[1] > 255 || a[2] < 0 || a[2] > 255 || a[3] < 0 || a[3] > 255) return 4;
    gains[a[0]][0] = a[1]; gains[a[0]][1] = a[2]; gains[a[0]][2] = a[3];
  } else if (!strcmp(op, "GO")) {
    if (n != 1) return 2;
    if (!configured) return 5;
    if (a[0] < 0) return 4;
    turns = a[0];
    watchdogFault = false;
    lastPeriodPulse = lastExposurePulse = 0xFFFFFFFF;
    startUs = micros();
    state = SWEEP;
  } else if (!strcmp(op, "LED")) {
    if (n != 4) return 2;
    if (state == SWEEP) return 5;
    if (a[0] < 0 || a[0] >= LED_COUNT || a[1] < 0 || a[1] > 255 || a[2] < 0 || a[2] > 255 || a[3] < 0 || a[3] > 255) return 4;
    ring.clear();
    setLed(a[0], a[1], a[2], a[3]);
    ring.show();
    watchdogFault = false;
    state = SINGLE;
  } else {
    return 3;
  }
  return 0;
}

void handleLine() {
  char scratch[MAX_LINE + 2];
  char body[MAX_LINE];
  if (overflow) {
    reply("-- ER 6", scratch);
    return;
  }
  line[lineLength] = '\0';
  char *star = strrchr(line, '*');
  if (line[0] != '#' || star == NULL || strlen(star) != 3) {
    reply("-- ER 2", scratch);
    return;
  }
  *star = '\0';
  char *frame = line + 1;
  char *frameEnd = frame + strlen(frame);
  if (strtol(star + 1, NULL, 16) != crc8(frame, strlen(frame))) {
    reply("-- ER 1", scratch);
    return;
  }
  char *id = strtok(frame, " ");
  char *op = strtok(NULL, " ");
  if (id == NULL || op == NULL || strlen(id) != 2) {
    reply("-- ER 2", scratch);
    return;
  }
  lastRxMs = millis();
  if (!strcmp(id, lastId)) {  // a retry: resend, never act twice
    Serial.print(lastReply);
    return;
  }
  char *rest = op + strlen(op) < frameEnd ? op + strlen(op) + 1 : (char *)"";
  char fields[MAX_LINE];
  int code = execute(op, rest, fields, sizeof(fields));
  if (code == 0) snprintf(body, sizeof(body), "%s OK%s", id, fields);
  else snprintf(body, sizeof(body), "%s ER %d", id, code);
  strncpy(lastId, id, sizeof(lastId));
  reply(body, lastReply);
}

void setup() {
  pinMode(PERIOD_PIN, OUTPUT);
  pinMode(EXPOSURE_PIN, OUTPUT);
  for (int i = 0; i < LED_COUNT; i++) gains[i][0] = gains[i][1] = gains[i][2] = 255;
  ring.begin();
  allOff();
  Serial.begin(115200);
  lastRxMs = millis();
}

void loop() {
  while (Serial.available() > 0) {
    char c = Serial.read();
    if (c == '\r') continue;
    if (c == '\n') {
      handleLine();
      lineLength = 0;
      overflow = false;
    } else if (lineLength < MAX_LINE) {
      line[lineLength++] = c;
    } else {
      overflow = true;
    }
  }
  if (state != IDLE && millis() - lastRxMs > watchdogMs) {  // silence: lights off (spec §3.5)
    state = IDLE;
    watchdogFault = true;
    allOff();
  }
  if (state == SWEEP) runSweep();
}
